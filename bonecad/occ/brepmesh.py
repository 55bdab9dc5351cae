"""BRepMesh triangles of one trimmed or analytic face, checked against its exact area.

Pitfall handled (DESIGN.md): ``BRepMesh_IncrementalMesh`` can cover only part of
a large periodic B-spline face. The face's triangulated area is compared with
its exact area from ``BRepGProp.SurfaceProperties_s`` with an explicit relative
tolerance (adaptive Gauss integration); a face short by more than the allowed
shortfall raises :class:`~bonecad.errors.KernelError`. Triangle edges longer
than ``max_edge_mm`` are bisected on the exact surface.
"""
from __future__ import annotations

import logging

import numpy as np
from OCP.BRep import BRep_Tool
from OCP.BRepGProp import BRepGProp
from OCP.BRepMesh import BRepMesh_IncrementalMesh
from OCP.GProp import GProp_GProps
from OCP.TopLoc import TopLoc_Location

from bonecad.errors import KernelError
from bonecad.mesh.sampling import triangle_areas
from bonecad.mesh.tessellation import TessellationSettings
from bonecad.occ.read_faces import native_to_spline_uv
from bonecad.splines.surface import BSplineSurface

log = logging.getLogger(__name__)


def brepmesh_face(face, index: int, surface: BSplineSurface | None, native: bool, is_reversed: bool,
                  settings: TessellationSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """BRepMesh triangles of one (trimmed or analytic) face: nodes, uv on ``surface``, triangles, exact area."""
    mesher = BRepMesh_IncrementalMesh(face, settings.deflection_mm, False, settings.angular_deflection_rad, True)
    if not mesher.IsDone():
        raise KernelError(f"BRepMesh_IncrementalMesh failed on face {index}")
    loc = TopLoc_Location()
    poly = BRep_Tool.Triangulation_s(face, loc)
    if poly is None or poly.NbTriangles() == 0:
        raise KernelError(f"face {index} has no triangulation after BRepMesh")
    trsf = loc.Transformation()
    count = poly.NbNodes()
    nodes = np.empty((count, 3))
    uv = np.empty((count, 2))
    for i in range(count):
        p = poly.Node(i + 1).Transformed(trsf)
        q = poly.UVNode(i + 1)
        nodes[i] = p.X(), p.Y(), p.Z()
        uv[i] = q.X(), q.Y()
    tri = np.array([poly.Triangle(i).Get() for i in range(1, poly.NbTriangles() + 1)], dtype=np.int64) - 1
    if is_reversed:
        tri = tri[:, [0, 2, 1]]
    mesh_area = triangle_areas(nodes, tri).sum()
    exact = exact_face_area(face, settings.area_rel_eps)
    if exact > 0 and (exact - mesh_area) / exact > settings.allowed_shortfall(exact):
        raise KernelError(
            f"face {index}: tessellation covers {mesh_area:.4g} mm^2 of {exact:.4g} mm^2 "
            f"({100 * mesh_area / exact:.2f} %); refusing a tessellation-based distance"
        )
    if surface is not None and not native:
        uv = native_to_spline_uv(face, surface, uv, nodes)
    nodes, uv, tri = _bisect_long_edges(nodes, uv, tri, surface, settings.max_edge_mm)
    return nodes, uv, tri, exact


def exact_face_area(face, rel_eps: float = 1e-6) -> float:
    """Area of one face (mm^2) by adaptive Gauss integration to relative error ``rel_eps``."""
    props = GProp_GProps()
    BRepGProp.SurfaceProperties_s(face, props, rel_eps)
    return float(props.Mass())


def _bisect_long_edges(nodes, uv, tri, surface, max_edge_mm: float):
    """Split triangles at the middle (in uv) of their longest edge until no edge exceeds max_edge_mm.

    The new node is placed on the exact surface when there is one. Neighbours are
    not split, so the result need not be conforming; distance queries do not
    need it to be.
    """
    nodes, uv, tri = nodes.copy(), uv.copy(), tri.copy()
    for _ in range(40):
        t = nodes[tri]
        lengths = np.stack([np.linalg.norm(t[:, (k + 1) % 3] - t[:, k], axis=1) for k in range(3)], axis=1)
        longest = np.argmax(lengths, axis=1)
        split = np.flatnonzero(lengths[np.arange(len(tri)), longest] > max_edge_mm)
        if len(split) == 0:
            break
        k = longest[split]
        a = tri[split, k]
        b = tri[split, (k + 1) % 3]
        c = tri[split, (k + 2) % 3]
        mid_uv = 0.5 * (uv[a] + uv[b])
        if surface is not None:
            mid = surface.evaluate(mid_uv[:, 0], mid_uv[:, 1]).points
        else:
            mid = 0.5 * (nodes[a] + nodes[b])
        new = len(nodes) + np.arange(len(split))
        nodes = np.concatenate([nodes, mid])
        uv = np.concatenate([uv, mid_uv])
        tri[split] = np.column_stack([a, new, c])
        tri = np.concatenate([tri, np.column_stack([new, b, c])])
    return nodes, uv, tri
