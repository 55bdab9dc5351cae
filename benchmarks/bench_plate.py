"""Benchmark of ``bonecad plate``: every bone x named region, the plate's fit, its screws and the times.

For the phantom, every tibia in ../shared/data/tibia and every femur in
../shared/data/femur: ``bonecad reconstruct`` (shipped settings; skipped when
--out already holds it), then ``bonecad plate`` on each named region of the
bone, once per screw direction (normal, the default, and transverse): whether
the solid is one valid solid, the share of the underside's samples within
gap + 0.5 mm, the largest gap and penetration (mm), the seat, the screws'
stock lengths and the checks they fail, and the plate's wall time (s; from the
reconstruction's folder: the plan, the solid and the files). Times are
measured on whatever machine runs it: on a loaded one they say little.

Run: python benchmarks/bench_plate.py [--out DIR] [--only STEM ...]
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import bonecad
from bonecad.errors import InputError
from bonecad.run.pipeline import patch_region, reconstruct, run_plate
from bonecad.settings import Settings, load_profile

DATA = Path(os.environ.get("BONECAD_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def inputs(folder: Path, only: list[str]) -> list[tuple[str, str, Path]]:
    """(name, bone, mesh file) of the phantom (written into ``folder``), every real tibia and femur."""
    phantom = folder / "phantom.stl"
    if not phantom.exists():
        bonecad.phantom_tibia().to_trimesh().export(phantom)
    found = [("phantom", "tibia", phantom)]
    for bone in ("tibia", "femur"):
        found += [(p.stem, bone, p) for p in sorted((DATA / bone).glob("*.stl"))]
    return [item for item in found if not only or item[0] in only]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="keep the reconstructions and plates here (default: a temporary "
                        "folder)")
    parser.add_argument("--only", nargs="*", default=[], help="mesh stems to run (default: all, and the phantom)")
    args = parser.parse_args()
    root = args.out or Path(tempfile.mkdtemp(prefix="bench-plate-"))
    root.mkdir(parents=True, exist_ok=True)
    print(f"{'mesh':<24s} {'region':<28s} {'direction':<10s} {'valid':>5s} {'<=g+0.5':>7s} {'gap':>5s} "
          f"{'pen':>5s} {'seat':>5s} {'g':>5s} {'s':>5s}  stock lengths (mm); failing checks", flush=True)
    for name, bone, mesh in inputs(root, args.only):
        run = root / name
        if not (run / "tspline.json").exists():
            start = time.perf_counter()
            reconstruct(mesh, run, Settings.load(None, {"pipeline": {"bone": bone}}))
            print(f"{name}: reconstructed in {time.perf_counter() - start:.1f} s", flush=True)
        for region_name in load_profile(bone).patch_regions:
            for direction in ("normal", "transverse"):
                settings = Settings.load(None, {"plate": {"screw_direction": direction}})
                region = patch_region(settings, region_name, None, None)
                start = time.perf_counter()
                try:
                    doc = run_plate(run, root / "plates" / f"{name}_{region_name}_{direction}", settings, region)
                except InputError as exc:
                    print(f"{name:<24s} {region_name:<28s} {direction:<10s} input error: {exc}", flush=True)
                    continue
                seconds = time.perf_counter() - start
                fit = doc.plan.fit_summary()
                stock = " ".join(f"{s.stock_mm:g}" for s in doc.plan.screws)
                failing = "; ".join(f"{f['hole']}: {', '.join(f['why'])}" for f in doc.failing) or "none"
                print(f"{name:<24s} {region_name:<28s} {direction:<10s} {str(doc.check['valid']):>5s} "
                      f"{100 * fit['share_within_gap_plus_mm']['0.5']:6.2f}% {fit['largest_gap_mm']:5.2f} "
                      f"{fit['largest_penetration_mm']:5.2f} {fit['seat_mm']:5.2f} {doc.mass_g:5.1f} "
                      f"{seconds:5.1f}  {stock}; {failing}", flush=True)


if __name__ == "__main__":
    main()
