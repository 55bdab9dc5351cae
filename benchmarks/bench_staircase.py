"""Benchmark of the T-spline fit on a voxel staircase whose smooth bone is known.

The JIA MRI tibia is the marching-cubes surface of a binary 1 mm mask: its
vertices lie on a half-voxel lattice, and no smooth surface lies within
0.25 mm of 99 % of it. To measure what the fit makes of such data, a smooth
CT tibia (the truth) is turned into the same kind of staircase
(``bonecad.imaging.compare.staircase_mesh``: binary mask, marching cubes),
and the T-spline fitted to the staircase is compared with both. Printed per
mesh and voxel size:

- the staircase against the truth: the best any reconstruction judged
  against the staircase can show is this share within 0.25 mm (the truth
  itself scores it);
- the T-spline as `reconstruct` makes it (noise-aware stop) and with the
  noise stop off (refining until the control-point budget): control points,
  and deviation against the staircase and against the truth (the solid,
  100 k area-weighted samples each way).

Run: python benchmarks/bench_staircase.py [--voxel-mm 1.0 ...] [mesh.stl ...]
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import bonecad
from bonecad.analysis.deviation import shape_deviation
from bonecad.analysis.deviation import sample_surface
from bonecad.analysis.model import tessellation_settings
from bonecad.analysis.statistics import settings_band_edges, share_within
from bonecad.contours.curves import contour_curves
from bonecad.imaging.compare import distance_to_surface, staircase_mesh
from bonecad.mesh.intake import prepare_bone
from bonecad.occ.tessellate import tessellate
from bonecad.settings import Settings
from bonecad.tspline_model import build_tspline_model

#: the shipped settings; the [analysis] tessellation with 1 % coverage tolerance, and histogram bands (mm)
SETTINGS = Settings.load()
TESSELLATION = replace(tessellation_settings(SETTINGS.analysis), coverage_tolerance=0.01)
BANDS_MM = settings_band_edges(SETTINGS.analysis)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "tibia"
SMOOTH_MESHES = ("LHDL_CT_tibia_no_fib_r.stl", "TLEM2_CT_tibia_r.stl")  # CT, smooth to 0.25 mm (quadric test)
WITHIN_MM = 0.25


def deviation_line(model_shape, vertices, faces) -> str:
    dev = shape_deviation(vertices, faces, tessellate(model_shape, TESSELLATION), edges_mm=BANDS_MM,
                          sample_points=100_000)
    m2c, c2m = dev.mesh_to_cad, dev.cad_to_mesh
    return (f"mesh->CAD within {WITHIN_MM} mm {m2c.share_within(WITHIN_MM):.4f}, "
            f"max {np.abs(m2c.deviation_mm).max():.3f}, "
            f"RMS {m2c.stats.rms_mm:.3f} mm; CAD->mesh within {c2m.share_within(WITHIN_MM):.4f}, "
            f"max {np.abs(c2m.deviation_mm).max():.3f} mm")


def main(paths: list[Path], voxels_mm: list[float]) -> None:
    config = SETTINGS.replace("tspline", compare_tensor_product=False)
    no_noise_stop = config.replace("tspline", noise_factor=0.0)
    for path in paths:
        truth = bonecad.load_bone(path, settings=SETTINGS)
        for voxel in voxels_mm:
            vertices, faces = staircase_mesh(truth.vertices, truth.faces, voxel)
            stair = prepare_bone(vertices, faces, source=f"{path.name} staircase", settings=SETTINGS.mesh,
                                 plausible=SETTINGS.units)
            samples = sample_surface(stair.vertices, stair.faces, 100_000, seed=0)
            d = distance_to_surface(truth.to_trimesh(), samples.points)
            w = samples.weights
            print(f"\n{path.name}, {voxel:g} mm voxels: staircase of {stair.triangle_count} triangles")
            print(f"  staircase vs truth: within {WITHIN_MM} mm {share_within(d, w, WITHIN_MM):.4f}, "
                  f"max {d.max():.3f}, RMS {np.sqrt(np.average(d**2, weights=w)):.3f} mm")
            frame = bonecad.anatomical_frame(stair, SETTINGS)
            contours = contour_curves(stair, frame, settings=SETTINGS.curves)
            for label, cfg in (("reconstruct (noise-aware stop)", config), ("noise stop off", no_noise_stop)):
                start = time.perf_counter()
                model = build_tspline_model(stair, frame, contours, settings=cfg.tspline,
                                            apex_hole_radius_mm=cfg.curves.apex_hole_radius_mm)
                seconds = time.perf_counter() - start
                print(f"  T-spline, {label}: {model.control_points} control points, {seconds:.1f} s; stopped: "
                      f"{model.fit.stopped}")
                print(f"    vs staircase: {deviation_line(model.shape, stair.vertices, stair.faces)}")
                print(f"    vs truth:     {deviation_line(model.shape, truth.vertices, truth.faces)}", flush=True)


if __name__ == "__main__":
    from threadpoolctl import threadpool_limits

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("meshes", nargs="*", type=Path)
    parser.add_argument("--voxel-mm", type=float, nargs="+", default=[1.0])
    args = parser.parse_args()
    with threadpool_limits(limits=1, user_api="blas"):  # as in `reconstruct` (bonecad.run.executor): same figures
        main(args.meshes or [DATA / name for name in SMOOTH_MESHES], args.voxel_mm)
