"""Planar sections of a closed triangle mesh, vectorised over triangles.

Each crossing triangle gives one segment; segments are oriented so every
closed loop runs counter-clockwise seen from the plane normal (outer loops)
and their end points are keyed by the mesh edge they lie on, so loops chain
exactly (no tolerance matching).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Section:
    """The section of a mesh by one plane.

    segments : (k, 2, 3) float64, mm, oriented counter-clockwise about ``normal``
    edge_keys : (k, 2) int64, the mesh edge (as a key) each end point lies on
    area : mm^2 enclosed (outer loops positive, holes negative)
    centroid : (3,) mm, area centroid (NaN when the plane misses the mesh)
    """

    origin: np.ndarray
    normal: np.ndarray
    segments: np.ndarray
    edge_keys: np.ndarray
    area: float
    centroid: np.ndarray

    def loops(self) -> list[np.ndarray]:
        """Closed loops as (p, 3) point arrays (first point not repeated), largest first."""
        return [self.segments[order, 0] for order in _chain(self.edge_keys)]


def plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (u, v) with (u, v, normal) right-handed."""
    normal = normal / np.linalg.norm(normal)
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(helper, normal)
    u /= np.linalg.norm(u)
    return u, np.cross(normal, u)


def section_mesh(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, normal: np.ndarray) -> Section:
    """Section of a closed, outward-oriented mesh by the plane through ``origin`` with ``normal``."""
    normal = np.asarray(normal, dtype=np.float64)
    normal = normal / np.linalg.norm(normal)
    origin = np.asarray(origin, dtype=np.float64)
    heights = (vertices - origin) @ normal
    # Nudge vertices lying exactly on the plane so every crossing is proper.
    heights = np.where(heights == 0.0, 1e-12, heights)
    fh = heights[faces]
    positive = fh > 0
    count = positive.sum(axis=1)
    crossing = (count == 1) | (count == 2)
    tri = faces[crossing]
    th = fh[crossing]
    tp = positive[crossing]
    if len(tri) == 0:
        empty = np.zeros((0, 2, 3))
        return Section(origin, normal, empty, np.zeros((0, 2), np.int64), 0.0, np.full(3, np.nan))

    # The lone vertex (alone on its side) is index `lone`; the two crossed
    # edges are lone->next and lone->prev.
    lone_is_positive = tp.sum(axis=1) == 1
    lone = np.where(lone_is_positive, np.argmax(tp, axis=1), np.argmin(tp, axis=1))
    rows = np.arange(len(tri))
    nxt = (lone + 1) % 3
    prv = (lone + 2) % 3
    vi_l, vi_n, vi_p = tri[rows, lone], tri[rows, nxt], tri[rows, prv]
    h_l, h_n, h_p = th[rows, lone], th[rows, nxt], th[rows, prv]
    p_l, p_n, p_p = vertices[vi_l], vertices[vi_n], vertices[vi_p]
    a = p_l + ((h_l / (h_l - h_n))[:, None]) * (p_n - p_l)
    b = p_l + ((h_l / (h_l - h_p))[:, None]) * (p_p - p_l)
    # With outward CCW faces: the segment runs a->b when the lone vertex is
    # above the plane, b->a when it is below (keeps loops CCW about normal).
    start = np.where(lone_is_positive[:, None], a, b)
    end = np.where(lone_is_positive[:, None], b, a)
    n_vertices = len(vertices)
    key_ln = np.minimum(vi_l, vi_n) * n_vertices + np.maximum(vi_l, vi_n)
    key_lp = np.minimum(vi_l, vi_p) * n_vertices + np.maximum(vi_l, vi_p)
    key_start = np.where(lone_is_positive, key_ln, key_lp)
    key_end = np.where(lone_is_positive, key_lp, key_ln)
    segments = np.stack([start, end], axis=1)

    u, v = plane_basis(normal)
    s2 = np.stack([(start - origin) @ u, (start - origin) @ v], axis=1)
    e2 = np.stack([(end - origin) @ u, (end - origin) @ v], axis=1)
    cross = s2[:, 0] * e2[:, 1] - e2[:, 0] * s2[:, 1]
    area = 0.5 * cross.sum()
    if abs(area) > 1e-12:
        c2 = ((s2 + e2) * cross[:, None]).sum(axis=0) / (6.0 * area)
        centroid = origin + c2[0] * u + c2[1] * v
    else:
        centroid = np.full(3, np.nan)
    return Section(origin, normal, segments, np.stack([key_start, key_end], axis=1), float(area), centroid)


def _chain(edge_keys: np.ndarray) -> list[np.ndarray]:
    """Segment index orders of the closed loops, largest loop first."""
    if len(edge_keys) == 0:
        return []
    next_of = {int(k): i for i, k in enumerate(edge_keys[:, 0])}
    successor = np.array([next_of.get(int(k), -1) for k in edge_keys[:, 1]])
    seen = np.zeros(len(edge_keys), dtype=bool)
    loops = []
    for first in range(len(edge_keys)):
        if seen[first]:
            continue
        order = []
        i = first
        while i >= 0 and not seen[i]:
            seen[i] = True
            order.append(i)
            i = successor[i]
        loops.append(np.array(order))
    loops.sort(key=len, reverse=True)
    return loops


class LevelSections:
    """Sections of one mesh perpendicular to one axis at many levels, each touching only the faces it crosses."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, axis: np.ndarray):
        self.vertices, self.faces = vertices, faces
        self.origin = np.asarray(origin, dtype=np.float64)
        self.axis = axis / np.linalg.norm(axis)
        face_heights = ((vertices - self.origin) @ self.axis)[faces]
        self._low, self._high = face_heights.min(axis=1), face_heights.max(axis=1)

    def at(self, level: float) -> Section:
        """The section at ``level`` mm along the axis from the origin."""
        crossing = (self._low <= level) & (self._high >= level)
        return section_mesh(self.vertices, self.faces[crossing], self.origin + level * self.axis, self.axis)


def section_stack(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, axis: np.ndarray, levels: np.ndarray):
    """Areas (k,) and centroids (k, 3) of sections perpendicular to ``axis`` at ``levels`` (mm from origin)."""
    stack = LevelSections(vertices, faces, origin, axis)
    areas = np.empty(len(levels))
    centroids = np.empty((len(levels), 3))
    for i, level in enumerate(levels):
        sec = stack.at(float(level))
        areas[i], centroids[i] = sec.area, sec.centroid
    return areas, centroids


def line_crossings(loop: np.ndarray, axis: int, value: float) -> np.ndarray:
    """Sorted values of the other coordinate where a closed (p, 2) polygon crosses the line
    ``loop[:, axis] == value`` (mm); empty when the line misses it."""
    a = np.asarray(loop, dtype=np.float64)
    b = np.roll(a, -1, axis=0)
    other = 1 - axis
    da, db = a[:, axis] - value, b[:, axis] - value
    crossing = (da <= 0) != (db <= 0)
    t = da[crossing] / (da[crossing] - db[crossing])
    return np.sort(a[crossing, other] + t * (b[crossing, other] - a[crossing, other]))


def polygon_centroid(loop: np.ndarray) -> np.ndarray:
    """Area centroid (2,) of a closed (p, 2) polygon (mm)."""
    a = np.asarray(loop, dtype=np.float64)
    b = np.roll(a, -1, axis=0)
    cross = a[:, 0] * b[:, 1] - b[:, 0] * a[:, 1]
    return ((a + b) * cross[:, None]).sum(axis=0) / (3.0 * cross.sum())


def hull_edge_across(points: np.ndarray, axis: int, value: float, side: float) -> np.ndarray:
    """The (2, 2) end points of the convex hull edge of (n, 2) points that the line
    ``points[:, axis] == value`` crosses on the hull's ``side`` (+1: where the other coordinate is
    largest, -1: smallest): the line tangent to the points from that side across ``value``."""
    from scipy.spatial import ConvexHull

    pts = np.asarray(points, dtype=np.float64)
    hull = pts[ConvexHull(pts).vertices]  # counter-clockwise
    nxt = np.roll(hull, -1, axis=0)
    da, db = hull[:, axis] - value, nxt[:, axis] - value
    crossing = np.flatnonzero((da <= 0) != (db <= 0))
    t = da[crossing] / (da[crossing] - db[crossing])
    other = hull[crossing, 1 - axis] + t * (nxt[crossing, 1 - axis] - hull[crossing, 1 - axis])
    i = crossing[np.argmax(side * other)]
    return np.stack([hull[i], nxt[i]])
