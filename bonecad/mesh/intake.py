"""Read a bone mesh, clean it, find the tibia among its bodies, check units.

Reading is trimesh's (STL ascii/binary, OBJ, PLY, OFF); cleanup is MeshLab's
(pymeshlab): merge duplicate vertices, drop duplicate and degenerate faces,
repair non-manifold edges and vertices, close small holes, orient faces
coherently and outward. Every repair is counted and reported.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Literal

import numpy as np

from bonecad.errors import InputError
from bonecad.mesh.bodies import body_roles, body_shape, check_not_fused, choose_tibia, proximal_direction
from bonecad.mesh.bone_mesh import BodyInfo, BoneMesh
from bonecad.settings import MeshSettings, UnitsSettings

log = logging.getLogger(__name__)

Units = Literal["auto", "mm", "cm", "m"]
UNIT_SCALE_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
MESH_SUFFIXES = (".stl", ".obj", ".ply", ".off")


def read_mesh_file(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) and faces (m, 3) of a mesh file, exactly as stored; InputError if unusable."""
    import trimesh

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
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise InputError(f"cannot be read as a {path.suffix[1:].upper()} mesh ({type(exc).__name__}: {exc})",
                         path) from None
    vertices = np.asarray(getattr(loaded, "vertices", np.empty((0, 3))), dtype=np.float64)
    faces = np.asarray(getattr(loaded, "faces", np.empty((0, 3))), dtype=np.int64)
    if len(faces) == 0 or len(vertices) < 4:
        raise InputError("holds no triangles (empty, truncated or not a mesh)", path)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise InputError(f"faces are not triangles (shape {faces.shape})", path)
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InputError("faces index vertices that do not exist (truncated file?)", path)
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise InputError(f"{int(bad.sum())} vertices have NaN or infinite coordinates", path)
    return vertices, faces


def _clean(vertices: np.ndarray, faces: np.ndarray, max_hole_edges: int) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """MeshLab cleanup; returns the cleaned arrays and a list of what was repaired."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=vertices, face_matrix=faces.astype(np.int32)))
    repairs: list[str] = []

    def counted(filter_name: str, label: str, **kwargs) -> None:
        before_v, before_f = ms.current_mesh().vertex_number(), ms.current_mesh().face_number()
        getattr(ms, filter_name)(**kwargs)
        after_v, after_f = ms.current_mesh().vertex_number(), ms.current_mesh().face_number()
        if (before_v, before_f) != (after_v, after_f):
            repairs.append(f"{label}: vertices {before_v}->{after_v}, faces {before_f}->{after_f}")

    counted("meshing_remove_duplicate_vertices", "merged duplicate vertices")
    counted("meshing_remove_duplicate_faces", "removed duplicate faces")
    counted("meshing_remove_null_faces", "removed degenerate (zero-area) faces")
    counted("meshing_repair_non_manifold_edges", "repaired non-manifold edges")
    counted("meshing_repair_non_manifold_vertices", "repaired non-manifold vertices")
    counted("meshing_remove_unreferenced_vertices", "removed unreferenced vertices")
    counted("meshing_close_holes", f"closed holes up to {max_hole_edges} edges", maxholesize=max_hole_edges)
    mesh = ms.current_mesh()
    return mesh.vertex_matrix().astype(np.float64), mesh.face_matrix().astype(np.int64), repairs


def _bodies(vertices: np.ndarray, faces: np.ndarray):
    """Split into connected bodies, each oriented outward; largest volume first."""
    import trimesh

    whole = trimesh.Trimesh(vertices, faces, process=False)
    parts = whole.split(only_watertight=False)
    oriented = []
    for part in parts:
        trimesh.repair.fix_normals(part, multibody=False)
        oriented.append(part)
    oriented.sort(key=lambda p: -abs(p.volume))
    return oriented


def _principal_extent(points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Principal axis, length along it and the largest width across it (mm)."""
    centred = points - points.mean(axis=0)
    _, _, vt = np.linalg.svd(centred[:: max(1, len(points) // 20000)], full_matrices=False)
    along = centred @ vt[0]
    across = centred @ vt[1:].T
    width = float((across.max(axis=0) - across.min(axis=0)).max())
    return vt[0], float(np.ptp(along)), width


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


def load_bone(
    path: str | Path,
    *,
    units: Units = "auto",
    settings: MeshSettings,
    plausible: UnitsSettings,
) -> BoneMesh:
    """Read, clean and check a tibia mesh; keep the tibia body (found by anatomy), report the others.

    Raises InputError (naming the file) for unreadable files, wrong units, a
    tibia broken into pieces, or a tibia fused to a neighbouring bone.
    """
    vertices, faces = read_mesh_file(path)
    return prepare_bone(vertices, faces, source=path, units=units, settings=settings, plausible=plausible)


def prepare_bone(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    source: str | Path = "",
    units: Units = "auto",
    settings: MeshSettings,
    plausible: UnitsSettings,
) -> BoneMesh:
    """Clean raw mesh arrays and keep the tibia body (see ``load_bone``); ``source`` names them in errors.

    plausible : the tibia length range that tells the units."""
    path = Path(source) if source else None
    vertices, faces, repairs = _clean(vertices, faces, settings.max_hole_edges)
    bodies = _bodies(vertices, faces)
    if not bodies or abs(bodies[0].volume) <= 0:
        raise InputError("has no closed body with a volume", path)

    # units from the largest body (a tibia or a femur: both 15-150 mm wide)
    _, length, width = _principal_extent(bodies[0].vertices)
    scale = _detect_scale(length, width, units, path, plausible.tibia_length_mm)
    shapes = [body_shape(np.asarray(b.vertices) * scale, abs(b.volume) * scale**3, np.asarray(b.centroid) * scale)
              for b in bodies]
    length_range = (float(plausible.tibia_length_mm[0]), float(plausible.tibia_length_mm[1]))
    t = choose_tibia(shapes, settings, length_range)
    tibia = bodies[t]
    tibia_vertices = np.asarray(tibia.vertices, dtype=np.float64) * scale
    tibia_faces = np.asarray(tibia.faces, dtype=np.int64)
    up = proximal_direction(tibia_vertices, tibia_faces, shapes[t].centroid, shapes[t].axis)
    roles = body_roles(shapes, t, up, settings)
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
    order = np.argsort([role != "tibia" for role in roles], kind="stable")  # the tibia first, then by volume
    infos = [infos[i] for i in order]
    broken = [i for i in infos if i.role == "broken piece"]
    if broken:
        sizes = ", ".join(f"{b.length_mm:.0f} mm / {b.volume_mm3 / 1000:.0f} cm3" for b in (infos[0], *broken))
        raise InputError(
            f"the tibia seems broken into {1 + len(broken)} large pieces along its axis ({sizes}); "
            "bonecad does not guess how to join them: segment the bone as one body",
            path,
        )
    check_not_fused(tibia_vertices, tibia_faces, settings, length_range, path)
    dropped = infos[1:]
    if dropped:
        repairs.append("dropped " + ", ".join(
            f"{i.role} ({i.triangles} triangles, {i.volume_mm3 / 1000:.1f} cm3, {i.length_mm:.0f} mm)"
            for i in dropped))
    if scale != 1.0:
        repairs.append(f"scaled by {scale:g} to mm (--units {units})")

    return BoneMesh(
        vertices=tibia_vertices,
        faces=tibia_faces,
        source=str(source),
        units="mm",
        bodies=tuple(infos),
        repairs=tuple(repairs),
        watertight=bool(tibia.is_watertight),
    )
