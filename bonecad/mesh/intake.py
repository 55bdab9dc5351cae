"""Read a bone mesh, clean it, find the bone (the tibia or the femur) among its bodies, check units.

Reading is trimesh's (STL ascii/binary, OBJ, PLY, OFF: its format readers,
straight to arrays; a binary STL by its rule and arrays, here). Cleanup merges duplicate vertices, drops duplicate and
degenerate faces (vectorised, ``mesh.topology``); only a mesh with border or
non-manifold edges goes through MeshLab's repairs (pymeshlab: non-manifold
edges and vertices, small holes closed). Faces are oriented coherently and
outward per body. Every repair is counted and reported. A mesh much denser
than the tolerance needs gets a working copy (``mesh.working``), on which the
anatomy is read.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from collections.abc import Callable
from typing import Any, Literal

import numpy as np

from bonecad.errors import InputError
from bonecad.mesh.bodies import body_roles, body_shape, check_not_fused, choose_tibia, proximal_direction
from bonecad.mesh.bone_mesh import BodyInfo, BoneMesh
from bonecad.mesh.sampling import triangle_areas
from bonecad.mesh.topology import (EdgeCounts, body_measures, duplicate_faces, edge_counts,
                                   merge_duplicate_vertices, non_manifold_vertices, signed_volumes,
                                   vertex_components, worth_a_job)
from bonecad.mesh.working import with_working_copy
from bonecad.settings import MeshSettings, UnitsSettings

log = logging.getLogger(__name__)

Units = Literal["auto", "mm", "cm", "m"]
Kept = Literal["tibia", "femur"]
UNIT_SCALE_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
MESH_SUFFIXES = (".stl", ".obj", ".ply", ".off")


def read_mesh_file(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) and faces (m, 3) of a mesh file, exactly as stored; InputError if unusable."""
    path = Path(path)
    if not path.exists():
        raise InputError("file does not exist", path)
    if path.is_dir():
        raise InputError("is a folder, not a mesh file", path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(
            f"unsupported mesh format '{path.suffix}' (expected one of {', '.join(MESH_SUFFIXES)})", path
        )
    if path.stat().st_size == 0:
        raise InputError("file is empty", path)
    try:
        vertices, faces = _read_arrays(path)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise InputError(f"cannot be read as a {path.suffix[1:].upper()} mesh ({type(exc).__name__}: {exc})",
                         path) from None
    if len(faces) == 0 or len(vertices) < 4:
        raise InputError("holds no triangles (empty, truncated or not a mesh)", path)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise InputError(f"faces are not triangles (shape {faces.shape})", path)
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InputError("faces index vertices that do not exist (truncated file?)", path)
    if not np.isfinite(vertices).all():  # (per row only then: a reduction along rows of 3 is slow)
        bad = ~np.isfinite(vertices).all(axis=1)
        raise InputError(f"{int(bad.sum())} vertices have NaN or infinite coordinates", path)
    return vertices, faces


def _read_arrays(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) (float32 or float64, as stored) and faces (m, 3) int64 of a mesh file, by trimesh's
    reader for its format (no Trimesh object: its copies and caches cost more than the reading on a dense mesh)."""
    file_type = path.suffix.lower()[1:]
    if file_type == "stl" and (binary := _binary_stl(path)) is not None:
        return binary
    from trimesh.exchange.load import mesh_loaders

    with open(path, "rb") as file:
        loaded = mesh_loaders[file_type](file, file_type=file_type)
    parts = list(loaded["geometry"].values()) if "geometry" in loaded else [loaded]  # OBJ: one part per object
    parts = [p for p in parts if len(np.asarray(p.get("faces", ()))) and len(np.asarray(p.get("vertices", ())))]
    if not parts:
        return np.empty((0, 3)), np.empty((0, 3), dtype=np.int64)
    if len(parts) == 1:  # (no copy: an STL's arrays are hundreds of MB)
        return np.asarray(parts[0]["vertices"]).reshape(-1, 3), np.asarray(parts[0]["faces"], dtype=np.int64)
    offsets = np.cumsum([0] + [len(p["vertices"]) for p in parts[:-1]])
    vertices = np.concatenate([np.asarray(p["vertices"]).reshape(-1, 3) for p in parts])
    faces = np.concatenate([np.asarray(p["faces"], dtype=np.int64) + o for p, o in zip(parts, offsets)])
    return vertices, faces


#: a binary STL's triangle record: normal, three corners (float32), attribute bytes
_STL_RECORD = np.dtype([("normal", "<f4", (3,)), ("corners", "<f4", (3, 3)), ("attributes", "<u2")])


def _binary_stl(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """Vertices (3 m, 3) float32, one per corner, and faces (m, 3) of a binary STL, read as trimesh reads it
    (its rule: binary when the header's triangle count gives the file's length) without importing trimesh
    (0.6 s); None for any other file (ASCII, truncated, empty: trimesh's reader and its errors)."""
    with open(path, "rb") as file:
        header = file.read(84)
        if len(header) < 84:
            return None
        count = int(np.frombuffer(header, dtype="<u4", offset=80)[0])
        if count == 0 or path.stat().st_size != 84 + count * _STL_RECORD.itemsize:
            return None
        records = np.frombuffer(file.read(), dtype=_STL_RECORD)  # (np.fromfile: twice the time)
    return records["corners"].reshape(-1, 3), np.arange(3 * count, dtype=np.int64).reshape(-1, 3)


@dataclass(frozen=True)
class _Cleaned:
    """A cleaned mesh: vertices (float64), faces, their edges, the triangles' areas (mm^2, input units), what
    was repaired, and ``manifold()``: whether the faces form a closed manifold (asked once; from a job
    when ``_clean`` ran its last check beside)."""

    vertices: np.ndarray
    faces: np.ndarray
    edges: EdgeCounts
    area: np.ndarray
    repairs: list[str]
    manifold: Callable[[], bool]


def _note(repairs: list[str], label: str, before: tuple[int, int], after: tuple[int, int]) -> None:
    """Records in ``repairs`` what a cleanup step changed: (vertices, faces) counts before and after."""
    if before != after:
        repairs.append(f"{label}: vertices {before[0]}->{after[0]}, faces {before[1]}->{after[1]}")


def _clean(vertices: np.ndarray, faces: np.ndarray, beside: Callable[..., Any] | None = None) -> _Cleaned:
    """The vectorised cleanup: duplicate vertices and faces, degenerate faces and unreferenced vertices
    removed (in MeshLab's order). A result that is not ``manifold()`` (border or non-manifold edges or
    vertices) is not used: ``_repaired`` cleans the input with MeshLab instead.

    beside : runs part of the work elsewhere (an executor's ``submit``, or the runner's helper thread's,
        ``run.executor.helper_thread``) while this process does the rest:
        half the vertex merging, then the face checks while this process counts the edges of the faces as
        merged (used when the checks drop no face, the common case), then, on a dense mesh, the count of
        non-manifold vertices, so that the caller reads the bodies meanwhile (``_manifold``).
    """
    repairs: list[str] = []
    note = partial(_note, repairs)
    size = (len(vertices), len(faces))
    merged_vertices, merged = merge_duplicate_vertices(vertices, faces, beside=beside)
    merged_vertices = merged_vertices.astype(np.float64, copy=False)
    checks = beside(_face_checks, merged_vertices, merged) if beside is not None else None
    merged_edges = edge_counts(merged, len(merged_vertices)) if checks is not None else None
    duplicate, merged_area = checks.result() if checks is not None else _face_checks(merged_vertices, merged)
    unique, area = _rows(merged, ~duplicate), _rows(merged_area, ~duplicate)
    positive = area > 0
    proper, area = _rows(unique, positive), _rows(area, positive)
    used = np.zeros(len(merged_vertices), dtype=bool)
    used[proper] = True
    kept_vertices, kept_faces = ((merged_vertices, proper) if used.all() else
                                 (merged_vertices[used], (np.cumsum(used) - 1)[proper]))
    edges = (merged_edges if kept_faces is merged and merged_edges is not None else
             edge_counts(kept_faces, len(kept_vertices)))
    manifold = _manifold(kept_faces, edges, beside)
    note("merged duplicate vertices", size, size := (len(merged_vertices), len(merged)))
    note("removed duplicate faces", size, size := (len(merged_vertices), len(unique)))
    note("removed degenerate (zero-area) faces", size, size := (len(merged_vertices), len(proper)))
    note("removed unreferenced vertices", size, (len(kept_vertices), len(kept_faces)))
    return _Cleaned(kept_vertices, kept_faces, edges, area, repairs, manifold)


def _repaired(vertices: np.ndarray, faces: np.ndarray, max_hole_edges: int) -> _Cleaned:
    """MeshLab's cleanup and repairs (``_meshlab_clean``) of a mesh the vectorised cleanup leaves open or
    non-manifold, with the same figures as ``_clean``'s."""
    repairs: list[str] = []
    note = partial(_note, repairs)
    vertices, faces = _meshlab_clean(vertices, faces, max_hole_edges, note)
    return _Cleaned(vertices, faces, edge_counts(faces, len(vertices)), triangle_areas(vertices, faces), repairs,
                    lambda: True)


def _manifold(faces: np.ndarray, edges: EdgeCounts, beside: Callable[..., Any] | None = None
              ) -> Callable[[], bool]:
    """Whether ``faces`` (with their ``edges``) form a closed manifold, no border or non-manifold edge or
    vertex, as a function asked later: on a dense mesh (``worth_a_job``) with ``beside``, the vertices' fans
    (the last check, on a mesh whose every edge has two faces) are counted in a job meanwhile."""
    if edges.border_edges or edges.non_manifold_edges:
        return lambda: False
    if beside is None or not worth_a_job(len(faces)):
        fans = non_manifold_vertices(faces, edges)
        return lambda: fans == 0
    job = beside(non_manifold_vertices, faces, edges)
    return lambda: job.result() == 0


def _face_checks(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(m,) bool the faces that repeat an earlier one (``duplicate_faces``), (m,) their areas (mm^2)."""
    return duplicate_faces(faces), triangle_areas(vertices, faces)


def _rows(array: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """``array[kept]``, or ``array`` itself when every row is kept (no copy of a dense mesh's arrays)."""
    return array if kept.all() else array[kept]


def _meshlab_clean(vertices: np.ndarray, faces: np.ndarray, max_hole_edges: int, note
                   ) -> tuple[np.ndarray, np.ndarray]:
    """MeshLab's cleanup and repairs of a mesh that needs them: duplicate vertices, duplicate and degenerate
    faces, non-manifold edges and vertices, unreferenced vertices, small holes (``note`` records each)."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(vertices, dtype=np.float64),
                               face_matrix=faces.astype(np.int32)))

    def counted(filter_name: str, label: str, **kwargs) -> None:
        before = ms.current_mesh().vertex_number(), ms.current_mesh().face_number()
        getattr(ms, filter_name)(**kwargs)
        note(label, before, (ms.current_mesh().vertex_number(), ms.current_mesh().face_number()))

    counted("meshing_remove_duplicate_vertices", "merged duplicate vertices")
    counted("meshing_remove_duplicate_faces", "removed duplicate faces")
    counted("meshing_remove_null_faces", "removed degenerate (zero-area) faces")
    counted("meshing_repair_non_manifold_edges", "repaired non-manifold edges")
    counted("meshing_repair_non_manifold_vertices", "repaired non-manifold vertices")
    counted("meshing_remove_unreferenced_vertices", "removed unreferenced vertices")
    counted("meshing_close_holes", f"closed holes up to {max_hole_edges} edges", maxholesize=max_hole_edges)
    mesh = ms.current_mesh()
    return mesh.vertex_matrix().astype(np.float64), mesh.face_matrix().astype(np.int64)


@dataclass(frozen=True)
class _Body:
    """One connected body of the cleaned mesh: its own vertices (mm, input units) and faces, oriented outward."""

    vertices: np.ndarray
    faces: np.ndarray
    volume: float
    area: float  # mm^2 (input units)
    centroid: np.ndarray  # area-weighted mean of the triangle centres
    watertight: bool  # every edge shared by two faces


def _bodies(mesh: _Cleaned, beside: Callable[..., Any] | None = None) -> list[_Body]:
    """Split into connected bodies, each oriented coherently and outward; largest volume first.

    beside : on a dense mesh (``worth_a_job``), the bodies' areas, centroids and volumes are summed in a job of it
        (an executor's ``submit``) while this process splits the faces."""
    vertices, faces, edges, area = mesh.vertices, mesh.faces, mesh.edges, mesh.area
    count, vertex_body = vertex_components(edges)
    face_body = vertex_body[faces[:, 0]]
    measures = (beside(body_measures, vertices, faces, area, face_body, count)
                if beside is not None and worth_a_job(len(faces)) else None)
    edge_body = vertex_body[edges.low_vertex()]
    open_bodies = np.bincount(edge_body[edges.faces_per_edge != 2], minlength=count) > 0
    incoherent = np.bincount(edge_body[~edges.consistent], minlength=count) > 0
    narrow = face_body.astype(np.int16) if count <= np.iinfo(np.int16).max else face_body  # (a radix sort)
    face_order = np.argsort(narrow, kind="stable")  # each body's faces in input order
    face_bounds = np.r_[0, np.cumsum(np.bincount(face_body, minlength=count))]
    areas, centroids, volumes = (measures.result() if measures is not None else
                                 body_measures(vertices, faces, area, face_body, count))
    bodies = []
    for b in range(count):
        body_faces = faces[face_order[face_bounds[b] : face_bounds[b + 1]]]
        if len(body_faces) == 0:
            continue
        used = np.zeros(len(vertices), dtype=bool)
        used[body_faces] = True
        body_vertices, body_faces = vertices[used], (np.cumsum(used) - 1)[body_faces]
        volume, watertight, body_area = float(volumes[b]), not open_bodies[b], float(areas[b])
        if open_bodies[b] or incoherent[b]:
            body_faces, volume, watertight = _mended(body_vertices, body_faces)
            body_area = float(triangle_areas(body_vertices, body_faces).sum())  # with the holes filled
        if volume < 0:
            body_faces, volume = body_faces[:, ::-1], -volume
        bodies.append(_Body(body_vertices, np.ascontiguousarray(body_faces), volume, body_area, centroids[b],
                            watertight))
    bodies.sort(key=lambda body: -body.volume)
    return bodies


def _mended(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, float, bool]:
    """A body left open or with disagreeing orientations, mended by trimesh (holes of three or four edges
    filled, faces turned to agree): its faces, signed volume (mm^3) and whether it is closed now."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    trimesh.repair.fill_holes(mesh)
    trimesh.repair.fix_winding(mesh)
    mended = np.asarray(mesh.faces, dtype=np.int64)
    volume = float(signed_volumes(vertices, mended, np.zeros(len(mended), dtype=np.int64), 1)[0])
    return mended, volume, bool(mesh.is_watertight)


def _detect_scale(length: float, width: float, units: Units, path: Path | None,
                  length_range: tuple[float, float]) -> float:
    """Scale to mm; in auto mode a non-mm mesh is an error naming the --units option."""
    if units != "auto":
        return UNIT_SCALE_TO_MM[units]
    lo, hi = length_range
    if lo <= length <= hi or 15.0 <= width <= 150.0:
        return 1.0
    for name in ("cm", "m"):
        scale = UNIT_SCALE_TO_MM[name]
        if lo <= length * scale <= hi or 15.0 <= width * scale <= 150.0:
            raise InputError(
                f"the bone is {length:.4g} units long and {width:.4g} wide: that is a tibia in {name}, "
                f"not mm (a tibia is {lo:.0f}-{hi:.0f} mm long); pass --units {name} to read it",
                path,
            )
    raise InputError(
        f"the bone is {length:.4g} units long and {width:.4g} wide, which fits no unit (mm, cm, m) "
        f"for a tibia ({lo:.0f}-{hi:.0f} mm long); pass --units to say which it is",
        path,
    )


def longest_bone_mm(plausible: UnitsSettings) -> float:
    """The longest single bone (mm): the longer of the tibia's and the femur's plausible lengths."""
    return float(max(plausible.tibia_length_mm[1], plausible.femur_length_mm[1]))


def _scaled(vertices: np.ndarray, scale: float) -> np.ndarray:
    """``vertices * scale``, or ``vertices`` themselves in mm already (no copy of a dense mesh)."""
    return vertices if scale == 1.0 else vertices * scale


def load_bone(
    path: str | Path,
    *,
    units: Units = "auto",
    settings: MeshSettings,
    plausible: UnitsSettings,
    keep: Kept = "tibia",
    working_copy: Callable[..., BoneMesh] = with_working_copy,
    beside: Callable[..., Any] | None = None,
) -> BoneMesh:
    """Read, clean and check a bone mesh; keep the ``keep`` body (found by anatomy), report the others.

    working_copy : ``with_working_copy`` or a function of the same arguments and result (the runner's, which
        builds the mesh's closest-point tree meanwhile).
    beside : runs part of the cleanup elsewhere (a ``submit``, ``_clean``); None: all here.

    Raises InputError (naming the file) for unreadable files, wrong units, a
    tibia broken into pieces, or a bone fused to a neighbouring bone.
    """
    return prepare_bone(*read_mesh_file(path), source=path, units=units, settings=settings,  # (arrays not held)
                        plausible=plausible, keep=keep, working_copy=working_copy, beside=beside)


def prepare_bone(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    source: str | Path = "",
    units: Units = "auto",
    settings: MeshSettings,
    plausible: UnitsSettings,
    keep: Kept = "tibia",
    working_copy: Callable[..., BoneMesh] = with_working_copy,
    beside: Callable[..., Any] | None = None,
) -> BoneMesh:
    """Clean raw mesh arrays and keep one body (see ``load_bone``); ``source`` names them in errors.

    plausible : the tibia length range that tells the units.
    keep : the body kept from a leg (``BoneProfile.body``): the tibia, found first (the other bodies' roles
        are read from their place beside it), or the femur it names; a single body is kept either way."""
    path = Path(source) if source else None
    cleaned = _clean(vertices, faces, beside)
    closed = not (cleaned.edges.border_edges or cleaned.edges.non_manifold_edges)
    bodies = _bodies(cleaned, beside) if closed else []  # (while the vertices' fans are counted: usually good)
    if not cleaned.manifold():
        cleaned = _repaired(vertices, faces, settings.max_hole_edges)
        bodies = _bodies(cleaned)
    repairs = cleaned.repairs
    del vertices, faces, cleaned  # (the bodies hold their own arrays: 0.6 GB less for the copy at 8 M triangles)
    if not bodies or bodies[0].volume <= 0:
        raise InputError("has no closed body with a volume", path)

    # units from the largest body (a tibia or a femur: both 15-150 mm wide)
    shapes = [body_shape(b.vertices, b.volume, b.centroid) for b in bodies]  # input units
    scale = _detect_scale(shapes[0].length, shapes[0].width, units, path, plausible.tibia_length_mm)
    shapes = [replace(b, volume=b.volume * scale**3, length=b.length * scale, width=b.width * scale,
                      centroid=b.centroid * scale) for b in shapes]
    length_range = (float(plausible.tibia_length_mm[0]), float(plausible.tibia_length_mm[1]))
    t = choose_tibia(shapes, settings, length_range)
    tibia = bodies[t]
    bone = working_copy(BoneMesh(vertices=_scaled(tibia.vertices, scale), faces=tibia.faces, source=str(source),
                                      units="mm", watertight=tibia.watertight), settings,
                             area_mm2=tibia.area * scale**2)
    work = bone.work  # the anatomy is read on the working copy
    up = proximal_direction(work.vertices, work.faces, shapes[t].centroid, shapes[t].axis)
    roles = body_roles(shapes, t, up, settings)
    femurs = [i for i, role in enumerate(roles) if role == "femur"]
    k = t
    if keep == "femur":
        k = max(femurs, key=lambda i: shapes[i].volume) if femurs else t
        roles[k] = "femur"
        if k != t:
            kept = bodies[k]
            bone = working_copy(BoneMesh(vertices=_scaled(kept.vertices, scale), faces=kept.faces, source=str(source),
                                              units="mm", watertight=kept.watertight), settings,
                                     area_mm2=kept.area * scale**2)
            work = bone.work
    infos = [
        BodyInfo(
            triangles=int(len(body.faces)),
            volume_mm3=shape.volume,
            length_mm=shape.length,
            centroid=shape.centroid,
            role=role,
        )
        for body, shape, role in zip(bodies, shapes, roles)
    ]
    order = np.argsort([i != k for i in range(len(roles))], kind="stable")  # the kept body first, then by volume
    infos = [infos[i] for i in order]
    broken = [i for i in infos if i.role == "broken piece"]
    if broken and keep == "tibia":
        sizes = ", ".join(f"{b.length_mm:.0f} mm / {b.volume_mm3 / 1000:.0f} cm3" for b in (infos[0], *broken))
        raise InputError(
            f"the tibia seems broken into {1 + len(broken)} large pieces along its axis ({sizes}); "
            "to model the fractured bone, reduce it onto the other side's bone first: `bonecad reduce INPUT "
            "--template contralateral OTHER_SIDE.stl --out DIR` (or `bonecad reconstruct --reduce --template ...`)",
            path,
        )
    check_not_fused(work.vertices, work.faces, settings, longest_bone_mm(plausible), path)
    dropped = infos[1:]
    if dropped:
        repairs.append("dropped " + ", ".join(
            f"{i.role} ({i.triangles} triangles, {i.volume_mm3 / 1000:.1f} cm3, {i.length_mm:.0f} mm)"
            for i in dropped) + ("; --bone femur keeps the femur" if keep == "tibia" and femurs else ""))
    if scale != 1.0:
        repairs.append(f"scaled by {scale:g} to mm (--units {units})")
    return replace(bone, bodies=tuple(infos), repairs=tuple(repairs))
