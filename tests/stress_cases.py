"""Seeded generators of perturbed inputs for the stress suite (``benchmarks/stress.py``, ``tests/test_stress.py``).

Every case is made from a real bone of ../shared/data and knows what a correct answer is: a model within
the bars against its known truth (the unperturbed bone, moved, mirrored or scaled as the input was), or an
exit 2 whose message names the bone and what to do. ``make_cases(n, seed)`` gives the same list for the same
arguments; ``build_case(case, folder)`` writes its input (a mesh file or a NIfTI CT) and its truth mesh.

Kinds (the table's rows):

- ``contact``: a leg with one bone moved along the tibia's axis (talus, femur) or towards it across
  the axis (fibula; the patella towards the femur) until the narrowest joint space is ``gap_mm`` (1.5 mm
  down to an overlap of 1 mm), imaged as a knee-to-ankle CT at a clinical grid;
- ``ct``: the tibia with its fibula, talus, patella and the femur's end (knee to ankle), imaged at a
  clinical grid (0.5-1 mm pixels, 0.6-3 mm slices), with noise, blur and a tilted gantry;
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


#: every bone mesh of ../shared/data a mesh case is made from (tibia files: their largest body is the truth)
def bone_files() -> list[str]:
    """Relative paths of the tibia and femur meshes under ``DATA`` (sorted; [] without the data)."""
    names = [p.relative_to(DATA).as_posix() for folder in ("tibia", "tibia_pairs", "femur", "femur_pairs")
             for p in sorted((DATA / folder).glob("*.stl"))]
    return names


#: perturbation kinds on a mesh, and on a CT
MESH_KINDS = ("noise", "decimate", "defects", "cut", "rigid", "units", "mirror")
CT_KINDS = ("contact", "ct")
KINDS = CT_KINDS + MESH_KINDS
#: contact cases: the moving bones and their gaps (mm; negative: overlapping)
CONTACT_BONES = ("talus", "femur", "patella", "fibula")
GAP_RANGE_MM = (-1.0, 1.5)
#: clinical CT grids: in-plane pixel and slice spacing ranges (mm)
PIXEL_RANGE_MM = (0.5, 1.0)
SLICE_RANGE_MM = (0.6, 3.0)


def ct_bars(slice_mm: float) -> tuple[float, float]:
    """(share within 0.25 mm, max mm) a CT's model must meet against its truth (issue 48)."""
    return (0.99, 1.0) if slice_mm <= 1.0 + 1e-9 else (0.98, 1.5)


def make_cases(count: int, seed: int = 0, *, kinds: tuple[str, ...] = KINDS, sources: list[str] | None = None
               ) -> list[Case]:
    """``count`` cases, the kinds in turn, each with its own seed (``seed * 100003 + index``) and parameters
    drawn from it; the same arguments give the same list (and a longer list starts with a shorter one's)."""
    files = bone_files() if sources is None else sources
    subjects = [s for s in LEGS if all((DATA / f).is_file() for f in LEGS[s][:4])]
    cases = []
    for index in range(count):
        kind = kinds[index % len(kinds)]
        case_seed = seed * 100003 + index
        rng = np.random.default_rng(case_seed)
        if kind in CT_KINDS:
            if not subjects:
                continue
            source = subjects[int(rng.integers(len(subjects)))]
            pixel = round(float(rng.uniform(*PIXEL_RANGE_MM)), 2)
            slice_mm = round(float(rng.uniform(*SLICE_RANGE_MM)), 1)
            params: dict[str, Any] = {"pixel_mm": pixel, "slice_mm": slice_mm}
            if kind == "contact":
                params["bone"] = CONTACT_BONES[int(rng.integers(len(CONTACT_BONES)))]
                params["gap_mm"] = round(float(rng.uniform(*GAP_RANGE_MM)), 2)
            else:
                params["noise_hu"] = round(float(rng.uniform(10.0, 60.0)), 0)
                params["blur_mm"] = round(float(rng.uniform(0.3, 1.0)), 2)
                params["tilt_deg"] = round(float(rng.choice([0.0, rng.uniform(5.0, 25.0)])), 1)
            case = Case(f"{kind}-{source}-{case_seed}", kind, source, case_seed, params, "model",
                        ct_bars(slice_mm))
        else:
            if not files:
                continue
            tibias = [f for f in files if "tibia" in f]
            group = (tibias or files) if rng.random() < 0.5 else ([f for f in files if f not in tibias] or files)
            source = group[int(rng.integers(len(group)))]
            params = _mesh_params(kind, rng)
            expect = {"cut": "model or exit 2", "units": "exit 2" if params.get("flag") == "auto" else "model"}
            case = Case(f"{kind}-{Path(source).stem}-{case_seed}", kind, source, case_seed, params,
                        expect.get(kind, "model"), (0.99, 1.0))
        cases.append(case)
    return cases


def _mesh_params(kind: str, rng: np.random.Generator) -> dict[str, Any]:
    if kind == "noise":
        return {"rms_mm": round(float(np.exp(rng.uniform(np.log(0.05), np.log(1.0)))), 3),
                "wavelength_mm": round(float(rng.uniform(1.0, 10.0)), 1)}
    if kind == "decimate":
        return {"how": str(rng.choice(["coarse", "uneven"])), "edge_mm": round(float(rng.uniform(1.5, 4.0)), 1)}
    if kind == "defects":
        return {"slivers": int(rng.integers(0, 200)), "holes": int(rng.integers(0, 6)),
                "flipped_share": round(float(rng.uniform(0.0, 0.1)), 3),
                "duplicated_share": round(float(rng.uniform(0.0, 0.05)), 3)}
    if kind == "cut":
        return {"end": str(rng.choice(["low", "high"])), "cut_mm": round(float(rng.uniform(1.0, 8.0)), 1)}
    if kind == "rigid":
        return {"rotation": [round(float(x), 6) for x in _random_rotation(rng).ravel()],
                "translation_mm": [round(float(x), 2) for x in rng.uniform(-1000.0, 1000.0, 3)]}
    if kind == "units":
        return {"unit": str(rng.choice(["cm", "m"])), "flag": str(rng.choice(["auto", "given"]))}
    if kind == "mirror":
        return {"axis": int(rng.integers(3))}
    raise ValueError(f"unknown mesh kind {kind!r}")


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random rotation matrix (QR of a Gaussian matrix, signs fixed, det +1)."""
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


@dataclass(frozen=True)
class BuiltCase:
    """A case's input file, the extra command-line arguments it needs, its truth mesh (mm, the input's frame)
    and what the build measured (the achieved gap, the noisy mesh's own RMS from the truth, ...)."""

    path: Path
    args: tuple[str, ...]
    truth_vertices: np.ndarray
    truth_faces: np.ndarray
    facts: dict[str, Any]
    side: str | None = None  # the side a correct frame names (None: not checked)


def _bone_mesh(source: str):
    """The truth bone of a mesh file: its largest body (a tibia file's fibula left out), outward."""
    import trimesh

    mesh = max(trimesh.load(DATA / source, force="mesh").split(only_watertight=False), key=lambda b: abs(b.volume))
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def surface_deviation(truth_vertices: np.ndarray, truth_faces: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                      samples: int = 50000, seed: int = 0) -> tuple[float, float, float]:
    """(share within 0.25 mm, max mm, RMS mm) of the distances from area-uniform samples of the truth's surface
    to the mesh ``(vertices, faces)``: the metric the benchmark applies to a model, applied to an input."""
    from bonecad.mesh.closest import TriangleLocator

    rng = np.random.default_rng(seed)
    tri = truth_vertices[truth_faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pick = rng.choice(len(tri), samples, p=area / area.sum())
    points = (tri[pick] * rng.dirichlet(np.ones(3), samples)[:, :, None]).sum(axis=1)
    distance = TriangleLocator(vertices, faces).distance(points)
    return float(np.mean(distance <= 0.25)), float(distance.max()), float(np.sqrt(np.mean(distance**2)))


def _file_side(source: str) -> str | None:
    stem = Path(source).stem
    return {"r": "right", "l": "left"}.get(stem.rsplit("_", 1)[-1])


def build_case(case: Case, folder: Path) -> BuiltCase:
    """Write ``case``'s input into ``folder`` (created) and return it with its truth."""
    folder.mkdir(parents=True, exist_ok=True)
    if case.kind in CT_KINDS:
        return _build_ct(case, folder)
    return _build_mesh(case, folder)


def _write_mesh(path: Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    import trimesh

    trimesh.Trimesh(vertices, faces, process=False).export(path)
    return path


def _build_mesh(case: Case, folder: Path) -> BuiltCase:
    import trimesh

    rng = np.random.default_rng(case.seed)
    truth = _bone_mesh(case.source)
    whole = trimesh.load(DATA / case.source, force="mesh")  # the input keeps the file's other bodies
    vertices, faces = np.asarray(whole.vertices, dtype=np.float64), np.asarray(whole.faces, dtype=np.int64)
    tv, tf = np.asarray(truth.vertices, dtype=np.float64), np.asarray(truth.faces, dtype=np.int64)
    p, args, facts = case.params, [], {}
    side = _file_side(case.source)
    if case.kind == "noise":
        vertices = _smooth_noise(whole, p["rms_mm"], p["wavelength_mm"], rng)
    elif case.kind == "decimate":
        vertices, faces = _decimated(whole, p["how"], p["edge_mm"], rng)
    elif case.kind == "defects":
        vertices, faces = _defects(vertices, faces, p, rng)
    elif case.kind == "cut":
        cut = _cut(whole, p["end"], p["cut_mm"], cap=False)
        vertices, faces = np.asarray(cut.vertices), np.asarray(cut.faces)
        capped = max(_cut(truth, p["end"], p["cut_mm"], cap=True).split(only_watertight=False),
                     key=lambda b: abs(b.volume))
        tv, tf = np.asarray(capped.vertices), np.asarray(capped.faces)
    elif case.kind == "rigid":
        rotation, shift = np.reshape(p["rotation"], (3, 3)), np.asarray(p["translation_mm"])
        vertices, tv = vertices @ rotation.T + shift, tv @ rotation.T + shift
    elif case.kind == "units":
        scale = {"cm": 0.1, "m": 0.001}[p["unit"]]
        vertices = vertices * scale
        if p["flag"] == "given":
            args = ["--units", p["unit"]]
    elif case.kind == "mirror":
        flip = np.ones(3)
        flip[p["axis"]] = -1.0
        vertices, tv = vertices * flip, tv * flip
        faces, tf = faces[:, ::-1], tf[:, ::-1]
        side = {"right": "left", "left": "right"}.get(side or "")
    if case.kind in ("noise", "decimate"):  # the rough input's own deviation from the truth, as a model's
        share, worst, rms = surface_deviation(tv, tf, vertices, faces)
        facts.update(input_within_025=round(share, 4), input_max_mm=round(worst, 3), input_rms_mm=round(rms, 4))
    if "_MRI_" in case.source:
        # an MRI segmentation is rough itself (ICL's 2.6 mm facets, JIA's 1 mm voxel staircase): no smooth
        # surface holds 99 % within 0.25 mm of it; its roughness is its RMS from its own smoothed surface
        # (the Taubin smoothing tests/legs.py gives a leg before imaging it)
        smooth = _smoothed(truth.copy())
        _, _, roughness = surface_deviation(np.asarray(truth.vertices), np.asarray(truth.faces),
                                            np.asarray(smooth.vertices), np.asarray(smooth.faces))
        facts["mri_roughness_mm"] = round(roughness, 4)
        facts["input_rms_mm"] = round(max(facts.get("input_rms_mm", 0.0), roughness), 4)
    path = _write_mesh(folder / f"{case.case_id}.stl", vertices, faces)
    return BuiltCase(path, tuple(args), tv, tf, facts, side)


def _smooth_noise(mesh, rms_mm: float, wavelength_mm: float, rng: np.random.Generator) -> np.ndarray:
    """``mesh``'s vertices moved along their normals by a smooth random field: 24 plane waves of wavelength
    ``wavelength_mm`` in random directions and phases, scaled to ``rms_mm`` RMS over the vertices."""
    directions = rng.standard_normal((24, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    phases = rng.uniform(0.0, 2 * np.pi, 24)
    k = 2 * np.pi / wavelength_mm
    field = np.sin(np.asarray(mesh.vertices) @ directions.T * k + phases).sum(axis=1)
    field *= rms_mm / max(float(np.sqrt(np.mean(field**2))), 1e-12)
    return np.asarray(mesh.vertices) + np.asarray(mesh.vertex_normals) * field[:, None]


def _decimated(mesh, how: str, edge_mm: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Coarse: quadric decimation to about ``edge_mm`` edges; uneven: that, then the part of the mesh on one
    side of a random plane through it subdivided (edges half as long there), conforming (no cracks)."""
    edge = float(np.median(mesh.edges_unique_length))
    target = int(len(mesh.faces) * min(1.0, (edge / edge_mm) ** 2))
    coarse = mesh.simplify_quadric_decimation(face_count=max(target, 500))
    vertices, faces = np.asarray(coarse.vertices, dtype=np.float64), np.asarray(coarse.faces, dtype=np.int64)
    if how == "coarse":
        return vertices, faces
    normal = rng.standard_normal(3)
    normal /= np.linalg.norm(normal)
    side = (vertices[faces].mean(axis=1) - vertices.mean(axis=0)) @ normal > 0
    return _refined(vertices, faces, side)


def _refined(vertices: np.ndarray, faces: np.ndarray, chosen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Faces ``chosen`` split in 4 at their edges' midpoints; a face with one split edge bisected, one with two
    or more split as well (closure), so the mesh stays conforming (no T-junctions)."""
    chosen = chosen.copy()
    keys = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 3, 2), axis=2)  # (m, 3 edges, 2)
    codes = keys[:, :, 0] * (len(vertices) + 1) + keys[:, :, 1]
    while True:
        split = np.isin(codes, codes[chosen])
        more = ~chosen & (split.sum(axis=1) >= 2)
        if not more.any():
            break
        chosen |= more
    edges, index = np.unique(codes[split], return_inverse=True)
    mid = np.full(codes.shape, -1, dtype=np.int64)
    mid[split] = len(vertices) + index
    a, b = edges // (len(vertices) + 1), edges % (len(vertices) + 1)
    vertices = np.vstack([vertices, 0.5 * (vertices[a] + vertices[b])])
    out = [faces[~split.any(axis=1)]]
    f, m = faces[chosen], mid[chosen]  # edges (0-1, 1-2, 2-0) -> midpoints m0, m1, m2
    out += [np.column_stack(c) for c in ((f[:, 0], m[:, 0], m[:, 2]), (m[:, 0], f[:, 1], m[:, 1]),
                                         (m[:, 2], m[:, 1], f[:, 2]), (m[:, 0], m[:, 1], m[:, 2]))]
    one = ~chosen & split.any(axis=1)
    for e in range(3):  # bisect: the split edge (e, e+1) and the opposite vertex e+2
        rows = one & split[:, e]
        f, m = faces[rows], mid[rows, e]
        i, j, k = f[:, e], f[:, (e + 1) % 3], f[:, (e + 2) % 3]
        out += [np.column_stack([i, m, k]), np.column_stack([m, j, k])]
    return vertices, np.vstack(out)


def _defects(vertices: np.ndarray, faces: np.ndarray, p: dict[str, Any], rng: np.random.Generator
             ) -> tuple[np.ndarray, np.ndarray]:
    """Slivers (a face split at a point 0.1 % along an edge), holes (a vertex's fan of faces removed), flipped
    and duplicated faces."""
    faces = faces.copy()
    n = len(faces)
    # slivers: face (a, b, c) -> (a, m, c) + (m, b, c) with m a hair from a on edge ab (a needle and a normal face)
    picked = rng.choice(n, size=min(p["slivers"], n), replace=False)
    new_vertices = vertices[faces[picked, 0]] * 0.999 + vertices[faces[picked, 1]] * 0.001
    m = len(vertices) + np.arange(len(picked))
    extra = np.column_stack([m, faces[picked, 1], faces[picked, 2]])
    faces[picked, 1] = m
    vertices = np.vstack([vertices, new_vertices])
    faces = np.vstack([faces, extra])
    # holes: the faces around a few random vertices removed
    for centre in rng.choice(len(vertices) - len(picked), size=p["holes"], replace=False):
        faces = faces[~(faces == centre).any(axis=1)]
    flip = rng.random(len(faces)) < p["flipped_share"]
    faces[flip] = faces[flip][:, ::-1]
    dup = faces[rng.random(len(faces)) < p["duplicated_share"]]
    return vertices, np.vstack([faces, dup])


def _cut(mesh, end: str, cut_mm: float, *, cap: bool):
    """``mesh`` with ``cut_mm`` taken off its lowest or highest end along its principal axis (open, or capped)."""
    import trimesh

    centred = mesh.vertices - mesh.vertices.mean(axis=0)
    axis = np.linalg.svd(centred[:: max(1, len(centred) // 5000)], full_matrices=False)[2][0]
    heights = np.asarray(mesh.vertices) @ axis
    if end == "low":
        return trimesh.intersections.slice_mesh_plane(mesh, axis, axis * (heights.min() + cut_mm), cap=cap)
    return trimesh.intersections.slice_mesh_plane(mesh, -axis, axis * (heights.max() - cut_mm), cap=cap)


def _build_ct(case: Case, folder: Path) -> BuiltCase:
    """A knee-to-ankle CT of a leg (the femur cut 60 mm above the tibia's plateau), NIfTI: ``contact``, one bone
    moved to the case's joint space first; ``ct``, with the case's noise, blur and gantry tilt."""
    import trimesh

    from bonecad.imaging import mesh_to_ct
    from bonecad.imaging.volume import CTVolume, write_nifti

    p = case.params
    bodies = leg_bodies(case.source)
    facts: dict[str, Any] = {}
    noise, blur, tilt = p.get("noise_hu", 30.0), p.get("blur_mm", 0.4), p.get("tilt_deg", 0.0)
    if case.kind == "contact":
        bodies, gap, area = move_to_gap(bodies, p["bone"], p["gap_mm"])
        facts.update(gap_mm=round(gap, 3), contact_mm2=round(area, 0))
    # a knee-to-ankle field of view: the femur cut 60 mm above the tibia's plateau (its cut capped)
    top = float(bodies["tibia"].vertices[:, 2].max()) + 60.0
    meshes = [m if m.vertices[:, 2].max() < top else
              trimesh.intersections.slice_mesh_plane(m, [0, 0, -1], [0, 0, top], cap=True)
              for m in bodies.values()]
    mesh = trimesh.util.concatenate(meshes)
    vertices = np.asarray(mesh.vertices)
    # a gantry tilted by t about x: slice k is the plane z = k dz + y tan t; image the mesh in the unsheared
    # grid's frame and give the volume the sheared affine
    shear = np.eye(3)
    shear[2, 1] = np.tan(np.radians(tilt))
    grid_vertices = vertices @ np.linalg.inv(shear).T
    ct = mesh_to_ct(grid_vertices, np.asarray(mesh.faces), voxel_mm=(p["pixel_mm"], p["pixel_mm"], p["slice_mm"]),
                    noise_hu=noise, blur_mm=blur, seed=case.seed)
    affine = ct.affine.copy()
    affine[:3, :3] = shear @ affine[:3, :3]
    affine[:3, 3] = shear @ affine[:3, 3]
    ct = CTVolume(hu=ct.hu, affine=affine, source="")
    facts["voxels"] = list(ct.shape)
    path = write_nifti(ct, folder / f"{case.case_id}.nii.gz")
    tibia = bodies["tibia"]
    return BuiltCase(path, (), np.asarray(tibia.vertices), np.asarray(tibia.faces), facts, LEGS[case.source][4])
