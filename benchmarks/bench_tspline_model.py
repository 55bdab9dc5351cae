"""Benchmark of the T-spline tibia model on the real meshes: prints, per mesh,
control points (T-spline vs a tensor-product B-spline fitted to the same
tolerance), the fit figures (share within 0.25 mm, max, RMS, on the fit's
points: the vertices of a fine mesh, the edge midpoints of a coarse one), an
independent deviation check of the closed solid
(bonecad.analysis.shape_deviation, both directions), cap continuity and time.

Targets: 99 % within 0.25 mm, max <= 1 mm, RMS <= 0.1 mm; T-spline control
points <= 50 % of the tensor product's; T-spline stage well under 10 s.

Run: python benchmarks/bench_tspline_model.py [mesh.stl ...]
"""
from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import bonecad
from bonecad.analysis.deviation import shape_deviation
from bonecad.analysis.model import tessellation_settings
from bonecad.analysis.statistics import settings_band_edges
from bonecad.contours.curves import contour_curves
from bonecad.errors import KernelError
from bonecad.occ.tessellate import tessellate
from bonecad.settings import Settings
from bonecad.tspline_model import build_tspline_model

#: the shipped settings; the [analysis] tessellation with 1 % coverage tolerance, and histogram bands (mm)
SETTINGS = Settings.load()
TESSELLATION = replace(tessellation_settings(SETTINGS.analysis), coverage_tolerance=0.01)
BANDS_MM = settings_band_edges(SETTINGS.analysis)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "tibia"


def main(paths: list[Path]) -> None:
    for path in paths:
        bone = bonecad.load_bone(path, settings=SETTINGS)
        frame = bonecad.anatomical_frame(bone, SETTINGS)
        contours = contour_curves(bone, frame, settings=SETTINGS.curves)
        apex_hole = SETTINGS.curves.apex_hole_radius_mm
        t0 = time.perf_counter()
        model = build_tspline_model(bone, frame, contours, apex_hole_radius_mm=apex_hole,
                                    settings=replace(SETTINGS.tspline, compare_tensor_product=False))
        stage = time.perf_counter() - t0
        # the comparison surface is timed apart: it is not part of the model
        t1 = time.perf_counter()
        compared = build_tspline_model(bone, frame, contours, apex_hole_radius_mm=apex_hole,
                                       settings=replace(SETTINGS.tspline, compare_tensor_product=True))
        tp_time = compared.timings_s.get("tensor_product", float("nan"))
        t_all = time.perf_counter() - t1
        try:
            dev = shape_deviation(bone.vertices, bone.faces, tessellate(model.shape, TESSELLATION), edges_mm=BANDS_MM,
                                  sample_points=100_000)
        except KernelError as exc:  # the analysis refuses faces its tessellation covers badly
            dev, dev_error = None, str(exc)
        fs = model.fit.stats
        tp = compared.tensor_product_control_points
        print(f"\n{path.name}: {bone.triangle_count} triangles")
        print(f"  T-spline: {model.control_points} control points ({model.cap_control_points} more in the caps), "
              f"{model.tspline.extraction.n_elements} Bezier faces; fit {'met' if model.fit.converged else 'missed'}"
              f" the tolerances ({model.fit.stopped})")
        print(f"  tensor product: {tp} control points (converged: {compared.tensor_product_converged}; "
              f"{compared.tensor_product_fit.stopped}); ratio {model.control_points / tp:.3f}")
        print(f"  fit (its points: the vertices of a fine mesh, the edge midpoints of a coarse one): "
              f"within 0.25 mm {fs.share_within:.4f}, max {fs.max_mm:.3f} mm, RMS {fs.rms_mm:.4f} mm")
        if dev is None:
            print(f"  solid vs mesh: analysis refused the tessellation ({dev_error})")
        else:
            m2c, c2m = dev.mesh_to_cad, dev.cad_to_mesh
            print(f"  solid vs mesh (100 k samples): mesh->CAD within 0.25 mm {m2c.share_within(0.25):.4f}, "
                  f"max {np.abs(m2c.deviation_mm).max():.3f} mm, "
                  f"RMS {np.sqrt(np.average(m2c.deviation_mm**2, weights=m2c.weights)):.4f} mm; "
                  f"CAD->mesh within 0.25 mm {c2m.share_within(0.25):.4f}, max {np.abs(c2m.deviation_mm).max():.3f} mm")
        for cap in model.caps:
            print(f"  {cap.end} cap: ring normal angle max {cap.ring_angle_deg[0]:.2e} deg (G1), "
                  f"pole normal spread {cap.pole_spread_deg:.3f} deg")
        steps = ", ".join(f"{k} {v:.1f}" for k, v in model.timings_s.items())
        print(f"  time: T-spline stage {stage:.1f} s ({steps}); "
              f"tensor-product comparison {tp_time:.1f} s (whole second build {t_all:.1f} s)", flush=True)


if __name__ == "__main__":
    from threadpoolctl import threadpool_limits

    args = [Path(a) for a in sys.argv[1:]] or sorted(DATA.glob("*.stl"))
    with threadpool_limits(limits=1, user_api="blas"):  # as in `reconstruct` (bonecad.run.executor): same figures
        main(args)
