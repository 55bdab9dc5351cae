"""Fine tessellation of an OpenCascade shape, read into numpy and checked against the exact face areas.

Untrimmed spline faces (:func:`~bonecad.occ.read_faces.is_natural`) are
gridded in parameters, all in one batch (:mod:`bonecad.mesh.grid_tessellation`);
other faces are meshed by BRepMesh face by face (:mod:`bonecad.occ.brepmesh`).
Every node gets its exact surface normal; a face covered short of its exact area
raises :class:`~bonecad.errors.KernelError`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from bonecad.errors import KernelError
from bonecad.mesh.closest import vertex_normals
from bonecad.mesh.sampling import triangle_areas
from bonecad.mesh.tessellation import Tessellation, TessellationSettings
from bonecad.occ.brep import face_is_reversed, nonempty_faces
from bonecad.occ.brepmesh import brepmesh_face
from bonecad.occ.read_faces import face_spline_surface, is_natural
from bonecad.splines.surface import BSplineSurface, SurfaceSet
from bonecad.mesh.grid_tessellation import grid_tessellation

log = logging.getLogger(__name__)


def tessellate(shape, settings: TessellationSettings) -> Tessellation:
    """Tessellate ``shape`` (any TopoDS_Shape with faces) and read it into numpy (module doc).

    Raises KernelError when BRepMesh fails or leaves a face covered short of its
    exact area by more than ``settings.allowed_shortfall``.
    """
    if settings.deflection_mm <= 0 or settings.max_edge_mm <= 0 or settings.angular_deflection_rad <= 0:
        raise ValueError(
            f"deflection_mm, max_edge_mm and angular_deflection_rad must be > 0, got {settings.deflection_mm}, "
            f"{settings.max_edge_mm}, {settings.angular_deflection_rad}"
        )
    faces = nonempty_faces(shape)
    surfaces, natives, natural = _read_faces(faces)
    reversed_faces = np.array([face_is_reversed(face) for face in faces], dtype=bool)
    sset = SurfaceSet(surfaces)
    area_exact = np.zeros(len(faces))
    parts = []
    if natural.any():
        parts.append(_grid_part(sset, np.flatnonzero(natural).tolist(), reversed_faces, settings, area_exact))
    for index in np.flatnonzero(~natural).tolist():
        parts.append(_brepmesh_part(faces, index, surfaces, natives, reversed_faces, settings, area_exact))
    whole = _Part.concatenate(parts)
    normals = _exact_normals(sset, whole, reversed_faces)
    area_mesh = np.bincount(whole.triangle_face, weights=triangle_areas(whole.vertices, whole.triangles),
                            minlength=len(faces))
    _check_coverage(area_exact, area_mesh, settings)
    return Tessellation(
        vertices=whole.vertices,
        triangles=whole.triangles,
        uv=whole.uv,
        normals=normals,
        node_face=whole.node_face,
        triangle_face=whole.triangle_face,
        face_area_exact_mm2=area_exact,
        face_area_mesh_mm2=area_mesh,
        surfaces=tuple(surfaces),
        reversed_faces=reversed_faces,
        faces=tuple(faces),
        surface_set=sset,
        native_faces=natives,
    )


@dataclass(frozen=True)
class _Part:
    """Triangles of some faces, nodes numbered from 0 (n nodes, m triangles).

    vertices : (n, 3) mm; uv : (n, 2); triangles : (m, 3) int; node_face, triangle_face : (n,), (m,) int;
    su, sv : (n, 3) S_u, S_v at the nodes where already evaluated (``evaluated`` (n,) bool), else 0
    """

    vertices: np.ndarray
    uv: np.ndarray
    triangles: np.ndarray
    node_face: np.ndarray
    triangle_face: np.ndarray
    su: np.ndarray
    sv: np.ndarray
    evaluated: np.ndarray

    @staticmethod
    def concatenate(parts: list[_Part]) -> _Part:
        """One part of all ``parts``, in order, their triangles renumbered."""
        offsets = np.cumsum([0] + [len(part.uv) for part in parts[:-1]])

        def joined(name: str) -> np.ndarray:
            return np.concatenate([getattr(part, name) for part in parts])

        return _Part(
            joined("vertices"), joined("uv"),
            np.concatenate([part.triangles + offset for part, offset in zip(parts, offsets)]),
            joined("node_face"), joined("triangle_face"), joined("su"), joined("sv"), joined("evaluated"),
        )


def _read_faces(faces: list) -> tuple[list[BSplineSurface | None], np.ndarray, np.ndarray]:
    """Each face's spline surface (None where conversion failed), and (F,) bool masks: native (on its
    own B-spline/Bezier surface), natural (native and its whole parameter rectangle)."""
    surfaces, natives, natural = [], [], []
    for face in faces:
        surface, native = face_spline_surface(face)
        surfaces.append(surface)
        natives.append(native)
        natural.append(surface is not None and native and is_natural(face, surface))
    return surfaces, np.array(natives, dtype=bool), np.array(natural, dtype=bool)


def _grid_part(sset: SurfaceSet, faces: list[int], reversed_faces: np.ndarray, settings: TessellationSettings,
               area_exact: np.ndarray) -> _Part:
    """The parameter grid of the natural ``faces``; their exact areas go into ``area_exact``."""
    grid = grid_tessellation(sset, faces, reversed_faces, settings, len(area_exact))
    area_exact[faces] = grid.area_mm2[faces]
    return _Part(grid.points, grid.uv, grid.triangles, grid.node_face, grid.triangle_face, grid.su, grid.sv,
                 np.ones(len(grid.uv), dtype=bool))


def _brepmesh_part(faces: list, index: int, surfaces: list, natives: np.ndarray, reversed_faces: np.ndarray,
                   settings: TessellationSettings, area_exact: np.ndarray) -> _Part:
    """BRepMesh triangles of face ``index``; its exact area goes into ``area_exact``."""
    nodes, uv, tri, area_exact[index] = brepmesh_face(
        faces[index], index, surfaces[index], natives[index], reversed_faces[index], settings
    )
    zeros = np.zeros_like(nodes)
    return _Part(nodes, uv, tri, np.full(len(nodes), index), np.full(len(tri), index), zeros, zeros,
                 np.zeros(len(nodes), dtype=bool))


def _exact_normals(sset: SurfaceSet, part: _Part, reversed_faces: np.ndarray) -> np.ndarray:
    """(n, 3) unit outward normals: exact where the face has a spline surface and the point is regular,
    else (poles, collapsed rows, faces without a surface) from the mesh."""
    normals = np.zeros_like(part.vertices)
    has = np.flatnonzero(sset.group[part.node_face] >= 0)
    if len(has):
        su, sv = part.su[has], part.sv[has]
        todo = ~part.evaluated[has]
        if todo.any():
            rest = has[todo]
            sample = sset.evaluate(part.node_face[rest], part.uv[rest, 0], part.uv[rest, 1], order=1)
            su[todo], sv[todo] = sample.du, sample.dv
        n = np.cross(su, sv)
        size = np.linalg.norm(n, axis=1, keepdims=True)
        good = size[:, 0] > 1e-10 * np.linalg.norm(su, axis=1) * np.linalg.norm(sv, axis=1)
        n = np.where(good[:, None], n / np.maximum(size, 1e-300), 0.0)
        normals[has] = np.where(reversed_faces[part.node_face[has]][:, None], -n, n)
    missing = np.linalg.norm(normals, axis=1) == 0
    if missing.any():
        normals[missing] = vertex_normals(part.vertices, part.triangles)[missing]
    return normals


def _check_coverage(area_exact: np.ndarray, area_mesh: np.ndarray, settings: TessellationSettings) -> None:
    """KernelError for the first face whose triangles fall short of its exact area (mm^2) by more than allowed."""
    short = (area_exact > 0) & (
        (area_exact - area_mesh) / np.where(area_exact > 0, area_exact, 1.0) > settings.allowed_shortfall(area_exact)
    )
    if short.any():
        index = int(np.flatnonzero(short)[0])
        raise KernelError(
            f"face {index}: tessellation covers {area_mesh[index]:.4g} mm^2 of {area_exact[index]:.4g} mm^2 "
            f"({100 * area_mesh[index] / area_exact[index]:.2f} %); refusing a tessellation-based distance"
        )
