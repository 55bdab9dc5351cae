"""Benchmark of what a CAD user does first with bonecad's models: the five operations on the re-read STEP.

For the phantom and every real mesh in ../shared/data/tibia: ``bonecad
reconstruct`` (shipped settings), then for nurbs.step and tspline.step: file
size, faces, re-read time (OpenCascade), and the five operations of
:mod:`bonecad.occ.operations` (offset 1 mm with arc joins, thick solid 1 mm,
osteotomy at mid-length, 3.5 mm drill through the shaft, mid-length section)
with their times; plus FreeCAD's verdict (headless ``freecadcmd``: one valid
closed solid) where FreeCAD is installed.

Run: python benchmarks/bench_cad_ops.py [--out DIR] [--only STEM ...]
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import bonecad
from bonecad.occ.exchange import read_named_step
from bonecad.occ.operations import run_cad_operations
from bonecad.run.pipeline import reconstruct
from bonecad.settings import Settings
from tests.freecad import freecad_check, freecad_command

DATA = Path(os.environ.get("BONECAD_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")) / "tibia"
OPERATIONS = ("offset", "thick_solid", "osteotomy", "drill", "section")


def inputs(folder: Path, only: list[str]) -> list[tuple[str, Path]]:
    """(name, mesh file) of the phantom (written into ``folder``) and of every real mesh."""
    phantom = folder / "phantom.stl"
    bonecad.phantom_tibia().to_trimesh().export(phantom)
    found = [("phantom", phantom)] + [(p.stem, p) for p in sorted(DATA.glob("*.stl"))]
    return [item for item in found if not only or item[0] in only]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="keep the reconstructions here (default: a temporary folder)")
    parser.add_argument("--only", nargs="*", default=[], help="mesh stems to run (default: all, and the phantom)")
    args = parser.parse_args()
    root = args.out or Path(tempfile.mkdtemp(prefix="bench-cad-"))
    root.mkdir(parents=True, exist_ok=True)
    settings = Settings.load()
    freecad = freecad_command()
    print(f"FreeCAD: {freecad or 'not installed (no FreeCAD check)'}")
    header = (f"{'mesh':<24s} {'model':<8s} {'MB':>5s} {'faces':>5s} {'read s':>6s} "
              + " ".join(f"{name:>12s}" for name in OPERATIONS) + "  FreeCAD")
    rows = []
    failures = 0
    for name, mesh in inputs(root, args.only):
        start = time.perf_counter()
        reconstruct(mesh, root / name, settings)
        print(f"{name}: reconstructed in {time.perf_counter() - start:.1f} s", flush=True)
        for model in ("nurbs", "tspline"):
            path = root / name / f"{model}.step"
            start = time.perf_counter()
            solid, named = read_named_step(path)
            read_s = time.perf_counter() - start
            ops = run_cad_operations(solid)
            cells = [f"{'ok' if op.passed else 'FAIL'} {op.seconds:5.1f}s" for op in ops]
            verdict = "-" if freecad is None else freecad_check(path).summary()
            failures += sum(not op.passed for op in ops)
            rows.append(f"{name:<24s} {model:<8s} {path.stat().st_size / 1e6:5.2f} {len(named):5d} {read_s:6.2f} "
                        + " ".join(f"{c:>12s}" for c in cells) + f"  {verdict}")
            for op in ops:
                if not op.passed:
                    rows.append(f"    {model} {op.name}: {op.problem}")
            print(rows[-1], flush=True)
    print()
    print(header)
    print("\n".join(rows))
    print(f"\n{failures} failed operations; outputs in {root}")


if __name__ == "__main__":
    main()
