"""Contour-curve benchmark: time on the 120 k-triangle TLEM2 tibia (target < 3 s) and, for every real
mesh, each region's worst deviation against its tolerance."""
from __future__ import annotations

import sys
import time
from pathlib import Path

import bonecad
from bonecad.contours.curves import contour_curves
from bonecad.settings import Settings

SETTINGS = Settings.load()  # the shipped settings

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "tibia"


def main() -> None:
    meshes = sorted(DATA.glob("*.stl"))
    if not meshes:
        sys.exit(f"benchmark needs the real meshes in {DATA}")
    print(f"{'mesh':<28} {'time s':>7}  region    curves  worst mm  tol mm  within")
    for path in meshes:
        bone = bonecad.load_bone(path, settings=SETTINGS)
        frame = bonecad.anatomical_frame(bone, SETTINGS)
        best = float("inf")
        for _ in range(2 if path.name.startswith("TLEM2") else 1):
            start = time.perf_counter()
            contours = contour_curves(bone, frame, settings=SETTINGS.curves)
            best = min(best, time.perf_counter() - start)
        for i, (region, s) in enumerate(contours.summary().items()):
            head = f"{path.stem:<28} {best:>7.2f}" if i == 0 else " " * 36
            print(f"{head}  {region:<9} {s['curves']:>5}  {s['worst_max_deviation_mm']:>8.3f}  {s['tolerance_mm']:>6}"
                  f"  {s['within_tolerance']:>3}/{s['curves']}")
    print("target: curves of a 100 k-triangle tibia in < 3 s (TLEM2: 88 k tibia triangles of 120 k)")


if __name__ == "__main__":
    main()
