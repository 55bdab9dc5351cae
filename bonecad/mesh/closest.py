"""Exact closest points on a triangle mesh, vectorised.

Closest point on one triangle: the foot on the triangle's plane when it lies
inside, else the nearest of the three clamped edge projections (the regions of
Ericson, *Real-Time Collision Detection* (2005), 5.1.5, evaluated branch-free).
The nearest triangle of each query point comes from libigl's bounding-box tree
(exact, C++), the points asked in a spatially coherent order (the leaf order
of a k-d tree of the points): each descent then finds the tree's nodes in
cache from the one before; the answers are the same as in any order
(each point's search is independent), in 2.4 times less CPU (100 k points
near a 120 k-triangle tibia: 0.40 -> 0.17 s, the k-d tree 0.02 s of it).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from bonecad.mesh.sampling import AREA_BLOCK, block_cross_products, spatial_order, triangle_areas


@dataclass(frozen=True)
class ClosestPoints:
    """points : (N, 3) closest points; triangle : (N,) index; barycentric : (N, 3); distance : (N,) mm."""

    points: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray
    distance: np.ndarray


def _frames(a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Per-triangle constants, (3, m) vectors as rows: a, e0 = b - a, e1 = c - a, e0.e0, e0.e1, e1.e1, 1/det.

    ``1/det`` is 0 for (near-)degenerate triangles: they are treated as their edges.
    """
    a = np.ascontiguousarray(np.asarray(a, dtype=np.float64).T)
    e0 = np.ascontiguousarray(np.asarray(b, dtype=np.float64).T) - a
    e1 = np.ascontiguousarray(np.asarray(c, dtype=np.float64).T) - a
    d00 = np.einsum("ij,ij->j", e0, e0)
    d01 = np.einsum("ij,ij->j", e0, e1)
    d11 = np.einsum("ij,ij->j", e1, e1)
    det = d00 * d11 - d01 * d01
    inv = np.divide(1.0, det, out=np.zeros_like(det), where=det > 1e-14 * d00 * d11)
    return a, e0, e1, d00, d01, d11, inv


def _kernel(p, a, e0, e1, d00, d01, d11, inv):
    """Barycentric (v, w) of the closest points (weights of b and c) for (3, n) points and triangles."""
    ap = p - a
    d20 = np.einsum("ij,ij->j", ap, e0)
    d21 = np.einsum("ij,ij->j", ap, e1)
    v = (d11 * d20 - d01 * d21) * inv
    w = (d00 * d21 - d01 * d20) * inv
    inside = (v >= 0) & (w >= 0) & (v + w <= 1) & (inv > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        # edge ab: a + t0 e0; edge ac: a + t1 e1; edge bc: b + t2 (e1 - e0) (zero length: the first vertex)
        t0 = np.clip(np.where(d00 > 0, d20 / d00, 0.0), 0.0, 1.0)
        t1 = np.clip(np.where(d11 > 0, d21 / d11, 0.0), 0.0, 1.0)
        e2 = e1 - e0
        bp = ap - e0
        d22 = np.einsum("ij,ij->j", e2, e2)
        t2 = np.clip(np.where(d22 > 0, np.einsum("ij,ij->j", bp, e2) / d22, 0.0), 0.0, 1.0)
    q = ap - t0 * e0
    s0 = np.einsum("ij,ij->j", q, q)
    q = ap - t1 * e1
    s1 = np.einsum("ij,ij->j", q, q)
    q = bp - t2 * e2
    s2 = np.einsum("ij,ij->j", q, q)
    use1 = s1 < s0
    use2 = s2 < np.minimum(s0, s1)
    ev = np.where(use2, 1.0 - t2, np.where(use1, 0.0, t0))
    ew = np.where(use2, t2, np.where(use1, t1, 0.0))
    return np.where(inside, v, ev), np.where(inside, w, ew)


def closest_point_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Closest points of ``p`` on triangles (a, b, c), row by row (all (N, 3)).

    Returns (closest (N, 3), barycentric (N, 3)). Degenerate triangles are handled
    as their edges (the nearest point on the nearest edge).
    """
    p = np.ascontiguousarray(np.asarray(p, dtype=np.float64).T)
    frame = _frames(a, b, c)
    v, w = _kernel(p, *frame)
    fa, e0, e1 = frame[:3]
    closest = fa + v * e0 + w * e1
    return np.ascontiguousarray(closest.T), np.column_stack([1.0 - v - w, v, w])


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(n, 3) unit vertex normals, area-weighted sums of the incident triangle normals."""
    fn = np.empty((3, len(triangles)))  # the face normals times twice their areas, in blocks
    for start in range(0, len(triangles), AREA_BLOCK):
        fn[:, start : start + AREA_BLOCK] = block_cross_products(vertices, triangles[start : start + AREA_BLOCK])
    corners = np.ascontiguousarray(triangles.T).ravel()  # corner 0 of every triangle, then 1, then 2
    acc = np.stack([np.bincount(corners, np.tile(fn[j], 3), minlength=len(vertices)) for j in range(3)], axis=1)
    return acc / np.maximum(np.linalg.norm(acc, axis=1, keepdims=True), 1e-300)


class TriangleLocator:
    """Exact closest-point queries on one triangle mesh (built once, queried many times).

    An axis-aligned bounding-box tree (libigl's ``AABB``, C++) finds each
    point's nearest triangle exactly; the barycentric coordinates of the foot
    point are then computed here (``closest_point_on_triangles``).

    vertices : (n, 3) float, mm; triangles : (m, 3) int
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray):
        import igl

        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.triangles = np.ascontiguousarray(triangles, dtype=np.int64)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise ValueError(f"vertices must be (n, 3), got {self.vertices.shape}")
        if self.triangles.ndim != 2 or self.triangles.shape[1] != 3 or len(self.triangles) == 0:
            raise ValueError(f"triangles must be (m, 3) with m > 0, got {self.triangles.shape}")
        if self.triangles.min() < 0 or self.triangles.max() >= len(self.vertices):
            raise ValueError("triangles index vertices out of range")
        self._tree = igl.AABB()
        self._tree.init(self.vertices, self.triangles)

    @cached_property
    def vertex_normals(self) -> np.ndarray:
        """(n, 3) the mesh's unit vertex normals (``vertex_normals``; computed at the first use, then kept)."""
        return vertex_normals(self.vertices, self.triangles)

    @cached_property
    def triangle_areas(self) -> np.ndarray:
        """(m,) mm^2: the area of each triangle (computed at the first use, then kept)."""
        return triangle_areas(self.vertices, self.triangles)

    @cached_property
    def spatial_order(self) -> np.ndarray:
        """(m,) the triangles in ``sampling.spatial_order`` (computed at the first use, then kept)."""
        return spatial_order(self.vertices, self.triangles)

    def _nearest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(squared distance (N,) mm^2, nearest triangle (N,)) of ``points`` (N, 3), asked of the tree in a
        coherent order (module doc) and returned in the points' own."""
        from scipy.spatial import cKDTree

        finite = np.flatnonzero(np.isfinite(points).all(axis=1))  # (a k-d tree takes finite points only)
        order = finite[cKDTree(points[finite], balanced_tree=False, compact_nodes=False).indices]
        if len(finite) < len(points):
            order = np.concatenate([order, np.flatnonzero(~np.isfinite(points).all(axis=1))])
        squared, triangle, _ = self._tree.squared_distance(self.vertices, self.triangles, points[order])
        squared_out, triangle_out = np.empty(len(points)), np.empty(len(points), dtype=np.int64)
        squared_out[order], triangle_out[order] = np.ravel(squared), np.ravel(triangle)
        return squared_out, triangle_out

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(N,) mm: the distance of each of ``points`` (N, 3) from the mesh (the tree's own, no closest points)."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        if len(points) == 0:
            return np.empty(0)
        return np.sqrt(self._nearest(points)[0])

    def query(self, points: np.ndarray) -> ClosestPoints:
        """Closest points of ``points`` (N, 3) on the mesh: the exact nearest point of every one."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must be (N, 3), got {points.shape}")
        if len(points) == 0:
            return ClosestPoints(np.empty((0, 3)), np.empty(0, dtype=np.int64), np.empty((0, 3)), np.empty(0))
        triangle = self._nearest(points)[1]
        tri = self.vertices[self.triangles[triangle]]
        closest, barycentric = closest_point_on_triangles(points, tri[:, 0], tri[:, 1], tri[:, 2])
        return ClosestPoints(closest, triangle, barycentric, np.linalg.norm(points - closest, axis=1))
