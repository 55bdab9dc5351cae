"""Vectorised topology of triangle meshes: duplicate vertices, edges, bodies, orientation.

Everything is sorting and counting over numpy arrays (no loop over vertices
or triangles), so a mesh of ten million triangles is analysed in seconds.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

#: odd 64-bit multipliers mixing the 32-bit words of a vertex into one hash (splitmix64 / xxhash constants)
_WORD_MIX = np.array([0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9, 0x27D4EB2F165667C5,
                      0x94D049BB133111EB, 0xBF58476D1CE4E5B9], dtype=np.uint64)


def first_of_equal_rows(rows: np.ndarray) -> np.ndarray:
    """(n,) for every row of ``rows`` (n, k) (float32/64 or int32/64), the index of the first row equal to it.

    Rows are grouped by a 64-bit hash of their bits (one sort), and every group
    is checked to hold one value (exact equality; a hash collision, never seen,
    falls back to sorting the rows themselves).
    """
    rows = np.ascontiguousarray(rows)
    words = rows.view(np.uint32).reshape(len(rows), -1)
    if words.shape[1] > len(_WORD_MIX):
        raise ValueError(f"rows of {words.shape[1]} 32-bit words: at most {len(_WORD_MIX)}")
    key = np.zeros(len(rows), dtype=np.uint64)
    with np.errstate(over="ignore"):
        for j in range(words.shape[1]):
            key ^= words[:, j].astype(np.uint64) * _WORD_MIX[j]
            key ^= key >> np.uint64(29)
    order = np.argsort(key)
    sorted_key = key[order]
    starts = np.flatnonzero(np.r_[True, sorted_key[1:] != sorted_key[:-1]])
    first = np.minimum.reduceat(order, starts)  # the lowest index of each group
    first_of = np.empty(len(rows), dtype=np.int64)
    first_of[order] = np.repeat(first, np.diff(np.r_[starts, len(order)]))
    if not np.array_equal(words, words[first_of]):
        _, first_exact, inverse = np.unique(rows.view(np.dtype((np.void, words.shape[1] * 4))).ravel(),
                                            return_index=True, return_inverse=True)
        first_of = first_exact[inverse.ravel()]
    return first_of


def merge_duplicate_vertices(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices with exactly equal coordinates merged into the first of them (the others dropped, the order
    kept, as MeshLab's ``meshing_remove_duplicate_vertices``); returns (vertices, faces re-indexed)."""
    vertices = np.ascontiguousarray(vertices) + 0.0  # -0.0 -> 0.0: equal coordinates, equal bits
    first_of = first_of_equal_rows(vertices)
    keep = first_of == np.arange(len(vertices))
    new_index = np.cumsum(keep) - 1
    return vertices[keep], new_index[first_of][faces]


def duplicate_faces(faces: np.ndarray) -> np.ndarray:
    """(m,) bool: the faces on the same three vertices as an earlier face (in any order)."""
    narrow = np.int32 if faces.size == 0 or faces.max() < np.iinfo(np.int32).max else np.int64  # fewer words to hash
    return first_of_equal_rows(np.sort(faces, axis=1).astype(narrow)) != np.arange(len(faces))


@dataclass(frozen=True)
class EdgeCounts:
    """The undirected edges of a mesh and how its faces use them.

    Half-edge ``3 f + k`` of face f runs from its corner k to corner k + 1 (mod 3).

    keys : (e,) int64, ``low * n + high`` of each edge's vertex indices, sorted
    faces_per_edge : (e,) faces using each edge (1: a border, more than 2: non-manifold)
    half_edges : (e, 2) two of the half-edges on each edge (both the first when it has one)
    consistent : (e,) a two-face edge is used once in each direction (the faces' orientations agree)
    """

    keys: np.ndarray
    faces_per_edge: np.ndarray
    half_edges: np.ndarray
    consistent: np.ndarray
    vertex_count: int

    @property
    def border_edges(self) -> int:
        return int(np.count_nonzero(self.faces_per_edge == 1))

    @property
    def non_manifold_edges(self) -> int:
        return int(np.count_nonzero(self.faces_per_edge > 2))

    def low_vertex(self) -> np.ndarray:
        """(e,) the lower vertex index of each edge."""
        return self.keys // self.vertex_count


def edge_counts(faces: np.ndarray, vertex_count: int) -> EdgeCounts:
    """The undirected edges of ``faces`` (indices below ``vertex_count``), counted (``EdgeCounts``)."""
    start = faces.ravel()
    end = faces[:, [1, 2, 0]].ravel()
    forward = start < end
    keys = np.where(forward, start, end).astype(np.int64) * vertex_count + np.where(forward, end, start)
    order = np.argsort(keys)
    sorted_keys = keys[order]
    starts = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])
    counts = np.diff(np.r_[starts, len(keys)])
    half = np.stack([order[starts], order[np.where(counts > 1, starts + 1, starts)]], axis=1)
    consistent = (counts != 2) | (forward[half[:, 0]] != forward[half[:, 1]])
    return EdgeCounts(sorted_keys[starts], counts, half, consistent, vertex_count)


def non_manifold_vertices(faces: np.ndarray, edges: EdgeCounts) -> int:
    """Vertices whose faces form more than one fan (joined through them alone), on a mesh whose every
    edge has two faces.

    Corner ``3 f + k`` is vertex ``faces[f, k]`` in face f; the next corner of
    its fan lies across its outgoing edge (where the twin half-edge ends). The
    fans are the cycles of that permutation, found by pointer doubling: each
    corner's label becomes the smallest corner within 2, 4, 8, ... steps
    along its cycle, until no label changes.
    """
    twin = np.empty(3 * len(faces), dtype=np.int64)
    first, second = edges.half_edges.T
    twin[first], twin[second] = second, first
    step = twin - twin % 3 + (twin % 3 + 1) % 3  # the corner the twin half-edge runs to
    label = np.arange(len(step))
    while True:
        smaller = np.minimum(label, label[step])
        if np.array_equal(smaller, label):
            break
        label, step = smaller, step[step]
    used = np.zeros(edges.vertex_count, dtype=bool)
    used[faces] = True
    return int(np.count_nonzero(label == np.arange(len(label)))) - int(np.count_nonzero(used))


def is_closed_and_oriented(faces: np.ndarray) -> bool:
    """Every edge of the mesh is shared by exactly two faces that run it in opposite directions."""
    edges = edge_counts(faces, int(faces.max()) + 1)
    return bool(np.all(edges.faces_per_edge == 2) and np.all(edges.consistent))


def vertex_components(faces: np.ndarray, vertex_count: int) -> tuple[int, np.ndarray]:
    """Bodies of a mesh (vertices joined by edges): (count, (n,) body of each vertex)."""
    a, b = faces.ravel(), faces[:, [1, 2, 0]].ravel()
    graph = sp.coo_matrix((np.ones(len(a), dtype=bool), (a, b)), shape=(vertex_count, vertex_count)).tocsr()
    count, labels = connected_components(graph, directed=False)
    return int(count), labels


def signed_volumes(vertices: np.ndarray, faces: np.ndarray, body_of_face: np.ndarray, bodies: int) -> np.ndarray:
    """(bodies,) mm^3: each body's enclosed volume, positive when its faces point outward."""
    tri = vertices[faces]
    six = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))
    return np.bincount(body_of_face, six, minlength=bodies) / 6.0
