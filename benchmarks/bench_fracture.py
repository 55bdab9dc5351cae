"""Benchmark of fracture reduction: fracture kind x template x bone, each fragment's error against the truth.

Each bone of ``../shared/data`` is broken by ``bonecad.imaging.fracture.fracture_bone`` (seeded: the distal
fragment turned by 20 degrees about a random axis, moved 15 mm across the axis and 10 mm along it, i.e.
shortened; with ``--butterfly``, a wedge of 3 % of the volume too) and reduced by
``bonecad.analysis.reduction.reduce_fragments`` onto

- ``mirror``: the bone's own mirror image, mirrored back (the contralateral of a perfectly symmetric patient:
  the method's floor), and
- ``contralateral``: the other side's bone mirrored (the left femur of each pair of ``femur_pairs/`` broken,
  the right one its template; the JIA tibia pair).

Columns: per fragment (proximal / distal / butterfly) the mean distance (mm) of its points to their place on the
intact bone once the whole reduced bone is aligned to the intact one, and its remaining rotation (degrees); for
a contralateral template also the same figures of the ideal registration (the intact fragments registered onto
the mirrored other side with their true periosteal surfaces: the template's own cost) and of the reduction
against that ideal. Times are wall seconds on a loaded machine.

Run: .venv/bin/python benchmarks/bench_fracture.py [--kinds transverse,oblique,spiral] [--butterfly]
     [--templates mirror,contralateral] [--bones NAME,...] [--seed 3]
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from bonecad.analysis.reduction import (FragmentBody, Template, ideal_placement, mirrored, placement_errors,
                                        reduce_fragments)
from bonecad.errors import InputError
from bonecad.imaging.fracture import apply, fracture_bone
from bonecad.mesh.intake import load_bone
from bonecad.settings import Settings

DATA = Path(os.environ.get("BONECAD_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
SETTINGS = Settings.load()


def _cases() -> list[tuple[str, str, Path, Path | None]]:
    """(name, bone, mesh, contralateral mesh or None) of every tibia and femur in the data."""
    cases = [(p.stem, "tibia", p, None) for p in sorted((DATA / "tibia").glob("*.stl"))
             if p.stem != "LHDL_CT_tibia_r"]  # (the same bone as LHDL_CT_tibia_no_fib_r)
    jia = DATA / "tibia_pairs" / "JIA_MRI_tibia_r.stl"
    cases = [(n, b, p, jia if n == "JIA_MRI_tibia_l" and jia.exists() else c) for n, b, p, c in cases]
    cases += [(p.stem, "femur", p, None) for p in sorted((DATA / "femur").glob("*.stl"))]
    for p in sorted((DATA / "femur_pairs").glob("*_l.stl")):  # the left femur broken, the right one its template
        other = p.with_name(p.stem[:-1] + "r.stl")
        if other.exists():
            cases.append((p.stem, "femur", p, other))
    return cases


def _load(path: Path, bone: str):
    """The bone's closed mesh (the intake's kept body; a femur longer than the intake's tibia range, which it
    refuses as fused, read as its largest body)."""
    try:
        mesh = load_bone(path, settings=SETTINGS.mesh, plausible=SETTINGS.units, keep=bone)  # type: ignore[arg-type]
    except InputError:
        import trimesh

        largest = max(trimesh.load(path).split(only_watertight=True), key=lambda b: b.volume)
        return np.asarray(largest.vertices, dtype=np.float64), np.asarray(largest.faces, dtype=np.int64)
    return np.asarray(mesh.vertices, dtype=np.float64), mesh.faces


def _template(vertices, faces, kind: str, source: str) -> Template:
    fr = SETTINGS.fracture
    return Template(vertices, faces, kind, source, fr.contralateral_uncertainty_mm, fr.contralateral_uncertainty_deg)


def _cell(errors: list[tuple[float, float]]) -> str:
    return " ".join(f"{mm:4.2f}/{deg:4.2f}" for mm, deg in errors)


def run_case(name: str, bone: str, path: Path, other: Path | None, kind: str, template_kind: str, butterfly: float,
             seed: int) -> str | None:
    vertices, faces = _load(path, bone)
    if template_kind == "mirror":
        if other is not None and bone == "femur":
            return None  # (the pairs' own mirrors: as the femurs of femur/ show, the floor is the same)
        template = _template(vertices, faces, "mirror", f"{name} mirrored twice")
    else:
        if other is None:
            return None
        tv, tf = _load(other, bone)
        tv, tf = mirrored(tv, tf, tv.mean(axis=0), np.array([1.0, 0.0, 0.0]))
        template = _template(tv, tf, "contralateral", other.stem)
    for attempt in range(5):
        try:
            fracture = fracture_bone(vertices, faces, kind=kind, bone=bone, butterfly_share=butterfly,  # type: ignore
                                     seed=seed + attempt, rotation_deg=20.0, translation_mm=15.0, shortening_mm=10.0)
            break
        except ValueError:
            continue
    else:
        return f"{name:22s} {kind:10s} {template_kind:13s} the cut failed for 5 seeds"
    bodies = [FragmentBody(f.vertices, f.faces, "intermediate" if f.role == "butterfly" else f.role)
              for f in fracture.fragments]
    start = time.perf_counter()
    reduction = reduce_fragments(bodies, template, SETTINGS.fracture, bone=bone)
    wall = time.perf_counter() - start
    placed = [apply(r.transform, f.vertices) for r, f in zip(reduction.fragments, fracture.fragments)]
    intact = [f.intact_vertices for f in fracture.fragments]
    errors = placement_errors(intact, placed)
    line = f"{name:22s} {kind:10s} {template_kind:13s} {wall:5.1f}s  reduced {_cell(errors)}"
    if template_kind == "contralateral":
        ideal = ideal_placement([(v, f.faces, f.fracture) for v, f in zip(intact, fracture.fragments)], template,
                                SETTINGS.fracture, bone=bone)
        ideal_placed = [apply(t, v) for t, v in zip(ideal, intact)]
        to_ideal = placement_errors(ideal_placed, [apply(t, f.vertices) for t, f in zip(
            [np.linalg.inv(reduction.fragments[0].transform) @ r.transform for r in reduction.fragments],
            fracture.fragments)])
        line += f" | ideal {_cell(placement_errors(intact, ideal_placed))} | vs ideal {_cell(to_ideal)}"
    poor = [f"{r.role} RMS {r.rms_mm:.2f}" for r in reduction.fragments if r.poor]
    return line + (f"  POOR: {', '.join(poor)}" if poor else "")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kinds", default="transverse,oblique,spiral")
    parser.add_argument("--templates", default="mirror,contralateral")
    parser.add_argument("--bones", default="", help="names (file stems) to run; all when empty")
    parser.add_argument("--butterfly", action="store_true", help="a butterfly wedge of 3 %% of the volume")
    parser.add_argument("--seed", type=int, default=3)
    args = parser.parse_args()
    wanted = set(filter(None, args.bones.split(",")))
    print("bone                   kind       template       wall    per fragment mm/deg (proximal distal [butterfly])")
    for name, bone, path, other in _cases():
        if wanted and name not in wanted:
            continue
        for template_kind in args.templates.split(","):
            for kind in args.kinds.split(","):
                line = run_case(name, bone, path, other, kind, template_kind, 0.03 if args.butterfly else 0.0,
                                args.seed)
                if line:
                    print(line, flush=True)


if __name__ == "__main__":
    main()
