"""Benchmark of the NURBS baseline: prints its figures and the targets.

- the NURBS stage (contours -> sewn, checked solid) on the 120 k-triangle TLEM2
  mesh, best of 3 (target < 5 s);
- for each real mesh in ../shared/data/tibia and both apex fills: faces,
  control points, volume difference against the mesh, worst compatible-curve
  refit, and the deviation bands (share of the mesh surface within
  0.1 / 0.25 / 0.5 / 1 mm of the model, largest deviation; 100 k samples,
  exact projection on the B-spline faces).

Run: python benchmarks/bench_nurbs.py [--samples N]
"""
from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import bonecad
from bonecad.analysis.deviation import shape_deviation
from bonecad.analysis.model import tessellation_settings
from bonecad.analysis.statistics import settings_band_edges
from bonecad.contours.curves import contour_curves
from bonecad.nurbs_model import build_nurbs
from bonecad.occ.tessellate import tessellate
from bonecad.settings import Settings

DATA = Path(os.environ.get("BONECAD_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")) / "tibia"
BANDS_MM = (0.1, 0.25, 0.5, 1.0)
SETTINGS = Settings.load()  # the shipped settings


def mesh_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    t = vertices[faces]
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


def bands(direction) -> tuple[list[float], float]:
    return [direction.share_within(b) for b in BANDS_MM], float(np.abs(direction.deviation_mm).max())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=100_000, help="deviation samples per direction")
    args = parser.parse_args()
    meshes = sorted(DATA.glob("*.stl"))
    if not meshes:
        raise SystemExit(f"no real meshes in {DATA}")
    settings = replace(tessellation_settings(SETTINGS.analysis), deflection_mm=0.05, max_edge_mm=1.5)
    histogram_edges = settings_band_edges(SETTINGS.analysis)  # the histograms (not printed) use the shipped bands
    header = (f"{'mesh':<24s} {'fill':<5s} {'tri':>7s} {'faces':>5s} {'poles':>6s} {'dV %':>7s} {'refit':>6s} "
              + " ".join(f"<{b:g}mm" for b in BANDS_MM) + "   max mm  (mesh->CAD | CAD->mesh)")
    lines = []
    for path in meshes:
        bone = bonecad.load_bone(path, settings=SETTINGS)
        frame = bonecad.anatomical_frame(bone, SETTINGS)
        contours = contour_curves(bone, frame, settings=SETTINGS.curves)
        if path.stem.startswith("TLEM2"):
            best = np.inf
            for _ in range(3):
                t0 = time.perf_counter()
                build_nurbs(contours, settings=replace(SETTINGS.nurbs, apex_fill="ring"))
                best = min(best, time.perf_counter() - t0)
            print(f"NURBS stage on {path.name} ({len(bone.faces)} triangles): {best:.2f} s (target < 5 s, best of 3)")
        vol = mesh_volume(bone.vertices, bone.faces)
        for fill in ("ring", "patch"):
            model = build_nurbs(contours, settings=replace(SETTINGS.nurbs, apex_fill=fill))
            result = shape_deviation(bone.vertices, bone.faces, tessellate(model.shape, settings),
                                     edges_mm=histogram_edges, sample_points=args.samples)
            fwd, fwd_max = bands(result.mesh_to_cad)
            back, back_max = bands(result.cad_to_mesh)
            refit = max(r.max_deviation_mm for r in model.refits)
            lines.append(
                f"{path.stem:<24s} {fill:<5s} {len(bone.faces):>7d} {model.faces:>5d} {model.control_points:>6d} "
                f"{100 * (model.volume_mm3 / vol - 1):>7.3f} {refit:>6.3f} "
                + " ".join(f"{s:>6.4f}" for s in fwd) + f"  {fwd_max:6.3f} | "
                + " ".join(f"{s:.4f}" for s in back) + f"  {back_max:6.3f}"
            )
            print(lines[-1], flush=True)
    print()
    print(header)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
