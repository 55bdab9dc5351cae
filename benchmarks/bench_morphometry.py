"""`bonecad measure`'s figures: the real tibias' parameters and the phantoms' recovery errors (README, `measure`).

Prints the parameters of every mesh in ../shared/data/tibia (or BONECAD_DATA/tibia) with the CPU time of
``measure_tibia`` (the frame not included), then, over the 20 varied phantoms of tests/test_morphometry.py,
the worst and mean error of each parameter against the phantom's design value (mm, degrees) and the CPU
time of a phantom's mesh and of its design values.

Run: .venv/bin/python benchmarks/bench_morphometry.py
"""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

import bonecad
from bonecad.anatomy.morphometry import PARAMETER_NAMES, measure_tibia
from bonecad.imaging.phantom_tibia import design_measurements, phantom_tibia
from bonecad.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from tests.cohorts import varied_parameters  # noqa: E402

DATA = Path(os.environ.get("BONECAD_DATA", ROOT.parent / "shared" / "data")) / "tibia"


def main() -> None:
    settings = Settings.load()
    columns: dict[str, dict[str, float]] = {}
    for path in sorted(DATA.glob("*.stl")):
        bone = bonecad.load_bone(path)
        frame = bonecad.anatomical_frame(bone)
        start = time.process_time()
        columns[path.stem] = measure_tibia(bone, frame, settings.morphometry).values()
        print(f"{path.name}: {frame.side}, measure_tibia {time.process_time() - start:.3f} s CPU")
    if columns:
        print(f"{'parameter':<30}" + "".join(f"{name[:16]:>18}" for name in columns))
        for name in PARAMETER_NAMES:
            print(f"{name:<30}" + "".join(f"{c[name]:>18.1f}" for c in columns.values()))

    errors: dict[str, list[float]] = {name: [] for name in PARAMETER_NAMES}
    mesh_s, design_s = [], []
    for params in varied_parameters():
        start = time.process_time()
        bone = phantom_tibia(params, settings=settings.mesh, plausible=settings.units)
        mesh_s.append(time.process_time() - start)
        measured = measure_tibia(bone, bonecad.anatomical_frame(bone), settings.morphometry).values()
        start = time.process_time()
        design = design_measurements(params, settings.morphometry)
        design_s.append(time.process_time() - start)
        for name in PARAMETER_NAMES:
            errors[name].append(measured[name] - design[name])
    print(f"\n{len(mesh_s)} phantoms: mesh {np.mean(mesh_s):.2f} s CPU each, design values {np.mean(design_s):.2f} s")
    print(f"{'parameter':<30}{'worst |error|':>15}{'mean error':>12}")
    for name, e in errors.items():
        print(f"{name:<30}{np.abs(e).max():>15.3f}{np.mean(e):>12.3f}")


if __name__ == "__main__":
    main()
