"""Where a ray crosses a triangle mesh (Moller-Trumbore against every triangle, vectorised).

A screw's axis is one ray through a bone of 10^4-10^5 triangles: a plain
pass over all of them takes milliseconds, no acceleration structure needed.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RayHits:
    """The crossings of one ray, nearest first: distance along the (unit) ray (mm), the point, and whether
    the ray leaves the solid there (True: along the triangle's outward normal)."""

    distance: np.ndarray  # (k,)
    points: np.ndarray  # (k, 3)
    leaving: np.ndarray  # (k,) bool


def ray_hits(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, direction: np.ndarray,
             *, eps: float = 1e-12) -> RayHits:
    """Every crossing of the ray ``origin + t * direction`` (t > 0, ``direction`` made unit) with the mesh;
    crossings closer than 1e-6 mm (a ray through an edge, counted by both triangles) are merged."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    o = np.asarray(origin, dtype=np.float64)
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    e1, e2 = b - a, c - a
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > eps
    inv = np.zeros_like(det)
    inv[ok] = 1.0 / det[ok]
    s = o - a
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = (q @ d) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    index = np.flatnonzero(hit)
    order = np.argsort(t[index])
    index, dist = index[order], t[index][order]
    if len(dist) > 1:  # the same crossing seen by two triangles (an edge or a vertex)
        keep = np.concatenate([[True], np.diff(dist) > 1e-6])
        index, dist = index[keep], dist[keep]
    normal = np.cross(e1[index], e2[index])
    return RayHits(dist, o + dist[:, None] * d, normal @ d > 0)
