"""Points that stand for a triangle mesh's surface in a least-squares fit.

A fit to the vertices alone integrates the distance with one point per
vertex; on a coarse mesh (edges of a few mm) that misses what the facets do
between the vertices, where the surface's deviation is measured too. Such a
mesh is subdivided at its edge midpoints (each triangle into four, same
surface) until its edges are short enough.
"""
from __future__ import annotations

import numpy as np


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(n,) mm^2: a third of the area of each vertex's triangles."""
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return np.bincount(faces.ravel(), np.repeat(area / 3.0, 3), minlength=len(vertices))


def median_edge_mm(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Median length of the triangles' edges (mm)."""
    tri = vertices[faces]
    return float(np.median(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2)))


def midpoint_subdivision(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each triangle split into four at its edge midpoints (the same surface, half the edge length).

    Returns (vertices (n + m, 3), faces (4 f, 3)): the original vertices
    first, then the midpoints of the m edges.
    """
    n = len(vertices)
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, inverse = np.unique(edges, axis=0, return_inverse=True)
    mid = n + inverse.reshape(-1, 3)  # midpoints of edges (a b), (b c), (c a) of each face
    a, b, c = faces.T
    ab, bc, ca = mid.T
    new_faces = np.concatenate([np.stack(f, axis=1) for f in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    new_vertices = np.vstack([vertices, 0.5 * (vertices[unique[:, 0]] + vertices[unique[:, 1]])])
    return new_vertices, new_faces


def fit_samples(vertices: np.ndarray, faces: np.ndarray, spacing_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The mesh's vertices, and midpoints of its edges until the median edge is at most ``spacing_mm``.

    Returns (points (k, 3), area weights (k,) mm^2): the vertices of the
    subdivided mesh (the original ones first) and a third of the area of
    their triangles.
    """
    while median_edge_mm(vertices, faces) > spacing_mm:
        vertices, faces = midpoint_subdivision(vertices, faces)
    return vertices, vertex_areas(vertices, faces)
