"""A fine tessellation of a CAD shape with exact-surface data per node, and its measured chord error.

Made by :func:`bonecad.occ.tessellate.tessellate`; used by the deviation
analysis and the renderer. numpy only: the faces it names are carried, not read.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import cached_property
from typing import overload

import numpy as np

from bonecad.mesh.sampling import triangle_areas
from bonecad.splines.surface import BSplineSurface, SurfaceSet
from bonecad.splines.project import project_faces

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TessellationSettings:
    """Tolerances of the tessellation (mm, rad), with the reason for each.

    deflection_mm : chord error aimed at (``tessellation_deflection_mm``). It
        bounds distances that are not refined on the exact surface (a tiny share
        of the samples; the colour map's vertex distances) and sets how close the
        Newton start is; the chord error is measured and reported, never assumed.
    angular_deflection_rad : largest turn of a surface normal along one edge.
    coverage_tolerance : relative area shortfall accepted per face. A chordal
        tessellation is short by about deflection/radius (1e-3 for 0.02 mm on a
        20 mm radius); 0.5 % leaves margin for that and still catches the
        known partial-coverage failure (20 % missing). A face only a few
        millimetres across is curved on its own scale, so it may fall short by
        up to ``small_face_factor`` x deflection / sqrt(area) (see :meth:`allowed_shortfall`).
    area_rel_eps : relative error asked of BRepGProp's adaptive integration
        (default settings were 1 % off on large B-spline faces).
    max_edge_mm : longest triangle edge (per parameter direction on grid faces;
        longer BRepMesh edges are bisected). The closest-point search assumes
        compact triangles.
    """

    deflection_mm: float
    angular_deflection_rad: float
    coverage_tolerance: float
    area_rel_eps: float
    max_edge_mm: float
    small_face_factor: float

    @overload
    def allowed_shortfall(self, exact_area_mm2: float) -> float: ...
    @overload
    def allowed_shortfall(self, exact_area_mm2: np.ndarray) -> np.ndarray: ...

    def allowed_shortfall(self, exact_area_mm2: float | np.ndarray) -> float | np.ndarray:
        """Relative area shortfall accepted for faces of these exact areas: the coverage
        tolerance, or the chordal shortfall of a face curved on its own size (a 1 mm^2
        cap face next to an apex), whichever is larger. A 20 % partial cover is still
        refused on every face above 0.25 mm^2 at 0.05 mm deflection."""
        size = np.sqrt(np.maximum(np.asarray(exact_area_mm2, dtype=np.float64), 1e-300))
        return np.maximum(self.coverage_tolerance, self.small_face_factor * self.deflection_mm / size)


@dataclass(frozen=True)
class Tessellation:
    """Triangles of every face of a shape, with exact-surface data per node.

    vertices : (n, 3) float, mm
    triangles : (m, 3) int, oriented so the right-hand normal points out of the
        material (face orientation applied)
    uv : (n, 2) float, parameters of each node on its face's spline surface
    normals : (n, 3) float, exact unit surface normals at the nodes, oriented like
        the triangles
    node_face, triangle_face : (n,), (m,) int, face index of each node / triangle
    face_area_exact_mm2, face_area_mesh_mm2 : (F,) float
    surfaces : one BSplineSurface per face, or None where the face could not be
        converted (distances on it stay tessellation-based)
    reversed_faces : (F,) bool, face orientation is REVERSED (flip S_u x S_v)
    chord_error_mm : (F,) float, measured largest distance between triangles
        (centroids, edge midpoints, circumcentres) and the exact surface; computed
        when first asked for (``chord_error_near`` measures only some triangles)
    """

    vertices: np.ndarray
    triangles: np.ndarray
    uv: np.ndarray
    normals: np.ndarray
    node_face: np.ndarray
    triangle_face: np.ndarray
    face_area_exact_mm2: np.ndarray
    face_area_mesh_mm2: np.ndarray
    surfaces: tuple[BSplineSurface | None, ...]
    reversed_faces: np.ndarray
    faces: tuple  # TopoDS_Face, in the order of the face index
    surface_set: SurfaceSet | None = None  # the surfaces packed for batched evaluation
    native_faces: np.ndarray | None = None  # (F,) bool, the face lies on its spline surface with the same (u, v)

    def __post_init__(self) -> None:
        if self.surface_set is None:
            object.__setattr__(self, "surface_set", SurfaceSet(self.surfaces))
        if self.native_faces is None:
            object.__setattr__(self, "native_faces", np.zeros(len(self.surfaces), dtype=bool))

    @property
    def face_count(self) -> int:
        return len(self.faces)

    @property
    def packed_surfaces(self) -> SurfaceSet:
        """``surface_set``, which ``__post_init__`` always fills."""
        if self.surface_set is None:
            raise ValueError("Tessellation.surface_set: not packed")
        return self.surface_set

    @cached_property
    def chord_error_mm(self) -> np.ndarray:
        return chord_errors(self.packed_surfaces, self.vertices, self.uv, self.triangles, self.triangle_face,
                            self.face_count)

    def chord_error_near(self, points: np.ndarray, distance_mm: np.ndarray) -> float:
        """Largest chord error (mm) of the triangles within reach of query points (0.0 for none).

        A point's distance measured on the tessellation (``distance_mm``) differs
        from its exact distance by at most the chord error of the triangles that
        come within that distance of it, plus one triangle; so only triangles whose
        centroid lies within distance + the longest triangle edge are measured.
        """
        from scipy.spatial import cKDTree

        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(points) == 0:
            return 0.0
        t = self.vertices[self.triangles]
        edge = max(float(np.linalg.norm(t[:, (k + 1) % 3] - t[:, k], axis=1).max()) for k in range(3))
        reach = np.abs(np.asarray(distance_mm, dtype=np.float64)) + edge
        hits = cKDTree(t.mean(axis=1)).query_ball_point(points, reach)
        near = np.unique(np.concatenate([np.asarray(h, dtype=np.int64) for h in hits]))
        if len(near) == 0:
            return 0.0
        chord = chord_errors(self.packed_surfaces, self.vertices, self.uv, self.triangles[near],
                             self.triangle_face[near], self.face_count)
        return float(chord.max())

    def triangle_areas(self) -> np.ndarray:
        return triangle_areas(self.vertices, self.triangles)


def chord_errors(sset: SurfaceSet, vertices, uv, triangles, triangle_face, face_count: int) -> np.ndarray:
    """(F,) largest distance (mm) from sampled triangle points to the exact surface, per face.

    Sampled on every triangle at the centroid, the edge midpoints and the
    circumcentre (where the chord error of a triangle inscribed in a sphere,
    the osculating surface, peaks; for an obtuse triangle it is the middle of
    the longest edge, sampled already). A measured value by exact projection,
    not BRepMesh's requested deflection (which BRepMesh exceeds by 2x on
    spheres). |p - S(uv)| at the sample's interpolated (u, v) is an upper
    bound of its distance; only samples whose bound exceeds the largest exact
    distance found so far on their face are projected, so the result is the
    exact maximum over all samples at a fraction of the projections. Faces
    without a spline surface get 0 (their triangles are the geometry).
    """
    chord = np.zeros(face_count)
    keep = sset.group[triangle_face] >= 0
    if not keep.any():
        return chord
    triangles, triangle_face = triangles[keep], triangle_face[keep]
    weights = np.array([[1 / 3, 1 / 3, 1 / 3], [0.5, 0.5, 0.0], [0.0, 0.5, 0.5], [0.5, 0.0, 0.5]])
    t = vertices[triangles]
    a2 = np.sum((t[:, 1] - t[:, 2]) ** 2, axis=1)
    b2 = np.sum((t[:, 2] - t[:, 0]) ** 2, axis=1)
    c2 = np.sum((t[:, 0] - t[:, 1]) ** 2, axis=1)
    cc = np.column_stack([a2 * (b2 + c2 - a2), b2 * (c2 + a2 - b2), c2 * (a2 + b2 - c2)])
    total = cc.sum(axis=1, keepdims=True)
    acute = np.all(cc > 0, axis=1)
    cc = np.where(acute[:, None], cc / np.where(total > 0, total, 1.0), 1 / 3)
    bary = np.concatenate([np.broadcast_to(weights, (len(t), 4, 3)), cc[:, None, :]], axis=1)
    pts = np.einsum("mwk,mkj->mwj", bary, t).reshape(-1, 3)
    start = np.einsum("mwk,mkj->mwj", bary, uv[triangles]).reshape(-1, 2)
    face = np.repeat(triangle_face, 5)
    bound = np.linalg.norm(pts - sset.evaluate(face, start[:, 0], start[:, 1]).points, axis=1)

    def exact(sel):
        proj = project_faces(sset, face[sel], pts[sel], start[sel])
        d = np.linalg.norm(pts[sel] - proj.foot, axis=1)
        converged = proj.residual_mm < 1e-6 + 1e-3 * d
        return np.where(converged, d, bound[sel])  # not converged: keep the upper bound

    # first each face's sample of largest bound
    order = np.lexsort((-bound, face))
    first = order[np.r_[True, face[order][1:] != face[order][:-1]]]
    np.maximum.at(chord, face[first], exact(first))
    # then the rest that could beat it, largest bound first, in growing batches: each
    # batch raises the maxima and drops the samples whose bound no longer exceeds them
    todo = np.flatnonzero(bound > chord[face])
    todo = todo[np.argsort(-bound[todo], kind="stable")]
    batch = 4096
    while len(todo):
        head, todo = todo[:batch], todo[batch:]
        np.maximum.at(chord, face[head], exact(head))
        todo = todo[bound[todo] > chord[face[todo]]]
        batch *= 4
    return chord
