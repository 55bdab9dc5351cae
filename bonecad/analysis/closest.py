"""Exact closest points on a triangle mesh, vectorised, with a certified candidate search.

For each query point the k triangles with the nearest centroids are tested
exactly (Ericson, *Real-Time Collision Detection* (2005), 5.1.5). Every triangle
lies in a ball of radius ``r_max`` about its centroid, so a triangle outside the
candidates is at least ``d_k - r_max`` away (``d_k``: the k-th centroid
distance). When ``d_k - r_max > d_best`` the answer is provably the nearest
triangle; points failing this test are searched again with more candidates,
and finally against every triangle within ``d_best + r_max`` of them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..errors import InputError


@dataclass(frozen=True)
class ClosestPoints:
    """points : (N, 3) closest points; triangle : (N,) index; barycentric : (N, 3); distance : (N,) mm."""

    points: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray
    distance: np.ndarray


def closest_point_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Closest points of ``p`` on triangles (a, b, c), row by row (all (N, 3)).

    Returns (closest (N, 3), barycentric (N, 3)). Degenerate triangles are handled
    as their longest edge would be (the region tests then select an edge or vertex).
    """
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    n = len(p)
    bary = np.zeros((n, 3))
    done = np.zeros(n, dtype=bool)

    def take(mask, w):
        nonlocal done
        m = mask & ~done
        bary[m] = w[m] if w.ndim == 2 else w
        done |= m

    take((d1 <= 0) & (d2 <= 0), np.array([1.0, 0.0, 0.0]))
    take((d3 >= 0) & (d4 <= d3), np.array([0.0, 1.0, 0.0]))
    take((d6 >= 0) & (d5 <= d6), np.array([0.0, 0.0, 1.0]))
    def ratio(num, den):  # a zero-length edge (den = 0): its first vertex
        return np.divide(num, den, out=np.zeros(n), where=den != 0)

    with np.errstate(divide="ignore", invalid="ignore"):
        v = ratio(d1, d1 - d3)
        take((vc <= 0) & (d1 >= 0) & (d3 <= 0), np.column_stack([1 - v, v, np.zeros(n)]))
        w = ratio(d2, d2 - d6)
        take((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.column_stack([1 - w, np.zeros(n), w]))
        w = ratio(d4 - d3, (d4 - d3) + (d5 - d6))
        take((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), np.column_stack([np.zeros(n), 1 - w, w]))
        denom = va + vb + vc
        v = vb / denom
        w = vc / denom
        inside = np.column_stack([1 - v - w, v, w])
    take(np.isfinite(inside).all(axis=1), inside)
    # anything left is a degenerate triangle: nearest of its three vertices
    rest = ~done
    if rest.any():
        dist = np.stack([np.linalg.norm(p - q, axis=1) for q in (a, b, c)], axis=1)
        bary[rest] = np.eye(3)[np.argmin(dist[rest], axis=1)]
    closest = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:3] * c
    return closest, bary


_BIG = 64


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(n, 3) unit vertex normals, area-weighted sums of the incident triangle normals."""
    tri = vertices[triangles]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    acc = np.zeros_like(vertices, dtype=np.float64)
    for k in range(3):
        np.add.at(acc, triangles[:, k], fn)
    return acc / np.maximum(np.linalg.norm(acc, axis=1, keepdims=True), 1e-300)


class TriangleLocator:
    """Closest-point queries on one triangle mesh (built once, queried many times).

    vertices : (n, 3) float, mm; triangles : (m, 3) int
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray):
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.triangles = np.asarray(triangles, dtype=np.int64)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise InputError(f"vertices must be (n, 3), got {self.vertices.shape}")
        if self.triangles.ndim != 2 or self.triangles.shape[1] != 3 or len(self.triangles) == 0:
            raise InputError(f"triangles must be (m, 3) with m > 0, got {self.triangles.shape}")
        if self.triangles.min() < 0 or self.triangles.max() >= len(self.vertices):
            raise InputError("triangles index vertices out of range")
        tri = self.vertices[self.triangles]
        centroids = tri.mean(axis=1)
        radii = np.linalg.norm(tri - centroids[:, None], axis=2).max(axis=1)
        # A few large triangles (planar caps) would make the certified radius
        # useless for all: test up to _BIG of the largest against every point.
        order = np.argsort(radii)[::-1]
        big = order[: min(_BIG, len(order) - 1)]
        big = big[radii[big] > 3.0 * np.median(radii)]
        small = np.setdiff1d(np.arange(len(radii)), big)
        self._big = big
        self._small = small
        self.centroids = centroids[small]
        self._radii = radii[small]
        self.radius = float(self._radii.max())
        self.tree = cKDTree(self.centroids)

    def _test(self, points, cand, mapped=False):
        """Best of candidate triangle lists ``cand`` (N, k) for each point.

        ``cand`` indexes the small-triangle KD-tree unless ``mapped`` (mesh indices).
        """
        n, k = cand.shape
        if not mapped:
            cand = self._small[cand]
        tri = self.triangles[cand.ravel()]
        rep = np.repeat(points, k, axis=0)
        cp, bary = closest_point_on_triangles(
            rep, self.vertices[tri[:, 0]], self.vertices[tri[:, 1]], self.vertices[tri[:, 2]]
        )
        d = np.linalg.norm(rep - cp, axis=1).reshape(n, k)
        best = np.argmin(d, axis=1)
        rows = np.arange(n) * k + best
        return cand[np.arange(n), best], cp[rows], bary[rows], d[np.arange(n), best]

    def _test_pairs(self, points, rows, tris):
        """Exact distances for (point row, mesh triangle) pairs."""
        tri = self.triangles[tris]
        cp, bary = closest_point_on_triangles(
            points[rows], self.vertices[tri[:, 0]], self.vertices[tri[:, 1]], self.vertices[tri[:, 2]]
        )
        return cp, bary, np.linalg.norm(points[rows] - cp, axis=1)

    def query(
        self, points: np.ndarray, *, k: int = 3, certify: bool = True, workers: int = -1
    ) -> ClosestPoints:
        """Closest points of ``points`` (N, 3) on the mesh.

        With ``certify`` (default) the result is the exact nearest point. Without,
        only the ``k`` triangles with the nearest centroids are tested: the result
        is a point on the mesh, the nearest one in all but rare cases (a first
        guess for exact projection, which does not need the certified one).
        """
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise InputError(f"points must be (N, 3), got {points.shape}")
        m = len(self._small)
        kk = min(k, m)
        dist, cand = self.tree.query(points, k=kk, workers=workers)
        if kk == 1:
            dist, cand = dist[:, None], cand[:, None]
        out_t, out_p, out_b, out_d = self._test(points, cand)
        todo = np.flatnonzero((kk < m) & (dist[:, -1] - self.radius <= out_d))
        if not certify:
            todo = todo[:0]
        kk = min(32, m)
        while len(todo):
            # every triangle that can beat the best so far has its centroid within
            # d_best + r_max; ask for them, test only those whose own radius allows it
            # (cKDTree takes one scalar bound: query in groups of similar bound)
            todo = todo[np.argsort(out_d[todo])]
            dist = np.empty((len(todo), kk))
            cand = np.empty((len(todo), kk), dtype=np.int64)
            for group in np.array_split(np.arange(len(todo)), min(16, len(todo))):
                bound = out_d[todo[group[-1]]] + self.radius + 1e-12
                dg, cg = self.tree.query(
                    points[todo[group]], k=kk, distance_upper_bound=bound, workers=workers
                )
                dist[group] = dg.reshape(len(group), kk)
                cand[group] = cg.reshape(len(group), kk)
            found = np.isfinite(dist)
            safe = np.where(found, cand, 0)
            useful = found & (dist - self._radii[safe] < out_d[todo][:, None])
            rows, cols = np.nonzero(useful)
            if len(rows):
                tris = self._small[cand[rows, cols]]
                cp, bary, d = self._test_pairs(points[todo], rows, tris)
                order = np.lexsort((d, rows))
                first = order[np.r_[True, rows[order][1:] != rows[order][:-1]]]
                sel = todo[rows[first]]
                better = d[first] < out_d[sel]
                sel, first = sel[better], first[better]
                out_t[sel], out_p[sel], out_b[sel], out_d[sel] = tris[first], cp[first], bary[first], d[first]
            complete = ~found[:, -1] | (kk == m)
            todo = todo[~complete]
            kk = min(kk * 4, m)
        if len(self._big):
            for lo in range(0, len(points), 8192):
                sl = slice(lo, lo + 8192)
                cand = np.broadcast_to(self._big, (len(points[sl]), len(self._big)))
                t, p, b, d = self._test(points[sl], cand, mapped=True)
                better = d < out_d[sl]
                idx = np.arange(lo, lo + len(d))[better]
                out_t[idx], out_p[idx], out_b[idx], out_d[idx] = t[better], p[better], b[better], d[better]
        return ClosestPoints(out_p, out_t, out_b, out_d)
