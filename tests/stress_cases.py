"""Seeded generators of perturbed inputs for the stress suite (``benchmarks/stress.py``, ``tests/test_stress.py``).

Every case is made from a real bone of ../shared/data and knows what a correct answer is: a model within
the bars against its known truth (the unperturbed bone, moved, mirrored or scaled as the input was), or an
exit 2 whose message names the bone and what to do. ``make_cases(n, seed)`` gives the same list for the same
arguments; ``build_case(case, folder)`` writes its input (a mesh file or a NIfTI CT) and its truth mesh.

Kinds (the table's rows):

- ``contact``: a whole leg with one bone moved along the tibia's axis (talus, femur) or towards it across
  the axis (fibula; the patella towards the femur) until the narrowest joint space is ``gap_mm`` (1.5 mm
  down to an overlap of 1 mm), imaged as a CT at a clinical grid;
- ``ct``: the tibia with its fibula, talus and the femur's end, imaged at a clinical grid (0.5-1 mm pixels,
  0.6-3 mm slices), with noise, blur and a tilted gantry;
- ``noise``: the tibia's mesh displaced along its normals by smooth noise of 0.05-1 mm RMS at 1-10 mm
  wavelengths;
- ``decimate``: coarse or uneven quadric decimation;
- ``defects``: slivers, holes, flipped and duplicated faces;
- ``cut``: a few mm cut off one end (the cut left open, as an export of a cropped scan);
- ``rigid``: any rotation and translation;
- ``units``: the mesh in cm or m;
- ``mirror``: the mesh mirrored (a right tibia becomes a left one).

Units: mm throughout (the ``units`` kind writes cm or m and its truth in mm).
"""
from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

DATA = Path(os.environ.get("BONECAD_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))

#: subject -> (tibia file (tibia and, except LHDL's no_fib, its fibula), femur, patella, talus, side, MRI)
LEGS: dict[str, tuple[str, str, str, str, str, bool]] = {
    "LHDL": ("tibia/LHDL_CT_tibia_r.stl", "femur/LHDL_CT_femur_r.stl", "leg/LHDL_CT_patella_r.stl",
             "leg/LHDL_CT_talus_r.stl", "right", False),
    "TLEM2": ("tibia/TLEM2_CT_tibia_r.stl", "femur/TLEM2_CT_femur_r.stl", "leg/TLEM2_CT_patella_r.stl",
              "leg/TLEM2_CT_talus_r.stl", "right", False),
    "ICL": ("tibia/ICL_MRI_tibia_r.stl", "femur/ICL_MRI_femur_r.stl", "leg/ICL_MRI_patella_r.stl",
            "leg/ICL_MRI_talus_r.stl", "right", True),
    "JIA": ("tibia/JIA_MRI_tibia_l.stl", "femur/JIA_MRI_femur_l.stl", "leg/JIA_MRI_patella_l.stl",
            "leg/JIA_MRI_talus_l.stl", "left", True),
}
#: Taubin smoothing of the MRI legs before imaging (as tests/legs.py: a CT images a bone, not another scan's
#: facets or staircase)
SMOOTHING_ITERATIONS = 20


def _smoothed(mesh):
    import trimesh

    if np.median(mesh.edges_unique_length) > 2.0:
        mesh = mesh.subdivide()
    trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=0.53, iterations=SMOOTHING_ITERATIONS)
    return mesh


@lru_cache(maxsize=4)
def leg_bodies(subject: str) -> dict[str, Any]:
    """The bones of ``subject``'s leg by name (tibia, fibula, femur, patella, talus; trimesh, mm, scanner
    coordinates), the MRI legs smoothed. Cached: callers must copy before changing one."""
    import trimesh

    tibia_file, femur, patella, talus, _, mri = LEGS[subject]
    bodies = sorted(trimesh.load(DATA / tibia_file, force="mesh").split(only_watertight=False),
                    key=lambda b: -abs(b.volume))
    named = {"tibia": bodies[0]}
    if len(bodies) > 1:
        named["fibula"] = bodies[1]
    for name, file in (("femur", femur), ("patella", patella), ("talus", talus)):
        named[name] = max(trimesh.load(DATA / file, force="mesh").split(only_watertight=False),
                          key=lambda b: abs(b.volume))
    if mri:
        named = {k: _smoothed(v) for k, v in named.items()}
    for mesh in named.values():
        if mesh.volume < 0:
            mesh.invert()
    return named


def _signed_distance(points: np.ndarray, mesh) -> np.ndarray:
    """Signed distance (mm) of ``points`` from a closed mesh's surface, negative inside (libigl, exact)."""
    import igl

    return np.asarray(igl.signed_distance(np.ascontiguousarray(points, dtype=np.float64),
                                          np.ascontiguousarray(mesh.vertices, dtype=np.float64),
                                          np.ascontiguousarray(mesh.faces, dtype=np.int64))[0])


def signed_gap(moving, fixed) -> float:
    """The narrowest space between two closed meshes (mm): the smallest distance from ``moving``'s vertices to
    ``fixed``'s surface, or, where they overlap, minus the deepest of its vertices inside ``fixed``."""
    return float(_signed_distance(moving.vertices, fixed).min())


def contact_area(moving, fixed, within_mm: float = 1.0) -> float:
    """Area (mm^2) of ``moving``'s surface within ``within_mm`` of ``fixed`` (or inside it)."""
    depth = _signed_distance(moving.triangles_center, fixed)
    return float(moving.area_faces[depth <= within_mm].sum())


#: moving bone -> the bone its joint space is measured against
PARTNER = {"talus": "tibia", "femur": "tibia", "fibula": "tibia", "patella": "femur"}


def contact_direction(bodies: dict[str, Any], bone: str) -> np.ndarray:
    """Unit direction ``bone`` moves in to close its joint: along the tibia's axis for the talus and femur,
    across it towards the partner's axis for the fibula and patella."""
    tibia = bodies["tibia"]
    centred = tibia.vertices - tibia.vertices.mean(axis=0)
    axis = np.linalg.svd(centred[:: max(1, len(centred) // 5000)], full_matrices=False)[2][0]
    partner = bodies[PARTNER[bone]]
    towards = partner.center_mass - bodies[bone].center_mass
    if bone in ("talus", "femur"):
        direction = axis * np.sign(towards @ axis)
    else:
        direction = towards - (towards @ axis) * axis
    return direction / np.linalg.norm(direction)


def move_to_gap(bodies: dict[str, Any], bone: str, gap_mm: float, *, tolerance_mm: float = 0.05
                ) -> tuple[dict[str, Any], float, float]:
    """A copy of ``bodies`` with ``bone`` moved rigidly (``contact_direction``) until its narrowest joint space
    with its partner is ``gap_mm`` (negative: overlapping by that much); (bodies, achieved gap mm, area mm^2
    of the bone within 1 mm of its partner)."""
    partner = bodies[PARTNER[bone]]
    direction = contact_direction(bodies, bone)
    source = bodies[bone]

    def gap_at(s: float):
        moved = source.copy()
        moved.apply_translation(s * direction)
        return moved, signed_gap(moved, partner)

    s = 0.0
    moved, gap = gap_at(s)
    for _ in range(30):  # secant-like steps: a small move changes the gap by about as much
        if abs(gap - gap_mm) <= tolerance_mm:
            break
        step = float(np.clip(gap - gap_mm, -20.0, 20.0))
        s += step
        moved, gap = gap_at(s)
    out = dict(bodies)
    out[bone] = moved
    return out, gap, contact_area(moved, partner)


@dataclass(frozen=True)
class Case:
    """One stress case: ``kind`` (the table's row), the source ``subject`` or file, its ``seed``, the perturbation's
    parameters, and what a correct answer is (``expect``: "model" within ``bars``, or "exit 2")."""

    case_id: str
    kind: str
    source: str
    seed: int
    params: dict[str, Any] = field(default_factory=dict)
    expect: str = "model"
    bars: tuple[float, float] = (0.99, 1.0)

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)
