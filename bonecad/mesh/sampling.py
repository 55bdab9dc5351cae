"""Points that stand for a triangle mesh's surface in a least-squares fit.

A fit to the vertices alone integrates the distance with one point per
vertex. On a fine mesh that is the surface; on a coarse one (edges of a few
mm) the vertices are the facets' corners, where a smooth surface through the
facets lies farthest from them, and what the facets do between the corners,
where the deviation is measured too, is missed. Such a mesh is sampled at
its edge midpoints instead: the edge-midpoint rule (weights a third of each
adjacent triangle's area) integrates every quadratic over a triangle
exactly, and the distance of a flat facet from a smooth surface varies
quadratically across it.
"""
from __future__ import annotations

import numpy as np


#: triangles per block of ``triangle_areas`` and ``closest.vertex_normals``: their temporaries stay in the cache
#: (TLEM2's leg split 64-fold, 7.7 M triangles: areas 0.23-0.33 s against 2.5 s in one go, most of it page
#: faults on fresh temporaries)
AREA_BLOCK = 32768


def block_cross_products(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The x, y and z components (each (f,)) of (b - a) x (c - a) for a block of triangles (a, b, c), written
    out: the same operations as ``np.cross``, without its temporaries."""
    a = np.take(vertices, faces[:, 0], axis=0)  # (np.take: several times faster than vertices[...] on rows)
    u, v = np.take(vertices, faces[:, 1], axis=0) - a, np.take(vertices, faces[:, 2], axis=0) - a
    return (u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1], u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2],
            u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])


def triangle_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(f,) mm^2: the area of each triangle (half the norm of the cross product of two edges, as
    ``np.linalg.norm`` without its temporaries), in blocks of ``AREA_BLOCK`` triangles."""
    areas = np.empty(len(faces))
    for start in range(0, len(faces), AREA_BLOCK):
        x, y, z = block_cross_products(vertices, faces[start : start + AREA_BLOCK])
        areas[start : start + AREA_BLOCK] = 0.5 * np.sqrt(x * x + y * y + z * z)
    return areas


#: (shift, mask) steps that spread a 21-bit integer's bits three apart (bit k to bit 3 k), for Morton codes
_SPREAD_STEPS = ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F), (4, 0x10C30C30C30C30C3),
                 (2, 0x1249249249249249))


def _spread_bits(values: np.ndarray) -> np.ndarray:
    """(n,) uint64: each of ``values``' (n,) low 21 bits moved to bit 3 k (the others zero)."""
    x = values.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in _SPREAD_STEPS:
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def spatial_order(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(f,) the triangles in the Z-order (Morton order) of their centroids on a 2^21 grid over the mesh's
    bounding box: triangles close in the order are close on the surface, so equal slices of the order's
    area are compact patches (``sample_surface`` draws one sample in each)."""
    corner_sums = (np.take(vertices, faces[:, 0], axis=0) + np.take(vertices, faces[:, 1], axis=0)
                   + np.take(vertices, faces[:, 2], axis=0))  # three times the centroids: the same grid cells
    low = corner_sums.min(axis=0)
    extent = max(float((corner_sums.max(axis=0) - low).max()), 1e-300)
    cells = ((corner_sums - low) * ((2**21 - 1) / extent)).astype(np.uint64)
    code = _spread_bits(cells[:, 0]) | (_spread_bits(cells[:, 1]) << np.uint64(1))
    code |= _spread_bits(cells[:, 2]) << np.uint64(2)
    order = np.argsort(code)  # (quicksort: a third of the stable sort's time, the same order without equal codes)
    ordered = code[order]
    return np.argsort(code, kind="stable") if (ordered[1:] == ordered[:-1]).any() else order


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(n,) mm^2: a third of the area of each vertex's triangles."""
    return np.bincount(faces.ravel(), np.repeat(triangle_areas(vertices, faces) / 3.0, 3), minlength=len(vertices))


def median_edge_mm(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Median length of the triangles' edges (mm)."""
    tri = vertices[faces]
    return float(np.median(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2)))


def _edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(m, 2) the unique edges (sorted vertex pairs) and (f, 3) each face's edges (a b), (b c), (c a) among them."""
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, inverse = np.unique(edges, axis=0, return_inverse=True)
    return unique, inverse.reshape(-1, 3)


def midpoint_subdivision(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each triangle split into four at its edge midpoints (the same surface, half the edge length).

    Returns (vertices (n + m, 3), faces (4 f, 3)): the original vertices
    first, then the midpoints of the m edges.
    """
    n = len(vertices)
    unique, face_edges = _edges(faces)
    mid = n + face_edges
    a, b, c = faces.T
    ab, bc, ca = mid.T
    new_faces = np.concatenate([np.stack(f, axis=1) for f in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    new_vertices = np.vstack([vertices, 0.5 * (vertices[unique[:, 0]] + vertices[unique[:, 1]])])
    return new_vertices, new_faces


def edge_midpoints(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The edge-midpoint quadrature of a mesh's surface: (points (m, 3), weights (m,) mm^2),
    one point per edge, weighted by a third of the area of the triangles beside it."""
    unique, face_edges = _edges(faces)
    weights = np.bincount(face_edges.ravel(), np.repeat(triangle_areas(vertices, faces) / 3.0, 3),
                          minlength=len(unique))
    return 0.5 * (vertices[unique[:, 0]] + vertices[unique[:, 1]]), weights


def fit_samples(vertices: np.ndarray, faces: np.ndarray, spacing_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Points at most about ``spacing_mm`` apart that stand for the mesh's surface, with their areas.

    A mesh whose median edge is at most ``spacing_mm`` gives its vertices
    (weights: a third of their triangles' area). A coarser one is split at
    its edge midpoints while its median edge exceeds twice ``spacing_mm``,
    and gives the midpoints of its edges (``edge_midpoints``, half an edge
    apart). Returns (points (k, 3), area weights (k,) mm^2).
    """
    points, weights, _ = fit_sample_mesh(vertices, faces, spacing_mm)
    return points, weights


def fit_sample_mesh(vertices: np.ndarray, faces: np.ndarray, spacing_mm: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``fit_samples`` and triangles joining its points (which lie beside which): the mesh's own, or, for
    edge midpoints, each triangle's middle triangle (its three edge midpoints, the same orientation).
    Returns (points (k, 3), area weights (k,) mm^2, triangles (m, 3) indices into the points)."""
    if median_edge_mm(vertices, faces) <= spacing_mm:
        return vertices, vertex_areas(vertices, faces), faces
    while median_edge_mm(vertices, faces) > 2.0 * spacing_mm:
        vertices, faces = midpoint_subdivision(vertices, faces)
    points, weights = edge_midpoints(vertices, faces)
    return points, weights, _edges(faces)[1]
