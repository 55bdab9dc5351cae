"""Analysis-suitability: no T-junction extension of one direction meets one
of the other (Li, Zheng, Sederberg, Hughes, Scott 2012, "On linear
independence of T-spline blending functions", CAGD 29, Def. 3.3 for cubics).

The extension of a T-junction lies on its stem's line: the *face extension*
runs from the T-junction into the face it points at, up to the second
perpendicular edge it crosses, and the *edge extension* runs back along the
stem up to the first one. In knot indices: [k-1, k+2] when the missing edge
points to +, [k-2, k+1] when it points to -, which is what ray casting from
the T-junction gives.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bonecad.splines.tspline.tmesh import TMesh


@dataclass(frozen=True)
class TJunctions:
    """The interior T-junctions of a T-mesh.

    points : (n, 2) int, [s-line, t-line].
    axis : (n,) int, 0 when the missing edge runs in s (extension along a
        t-line), 1 when it runs in t (extension along an s-line).
    extent : (n, 2) int, closed index range of the extension along its line
        (unwrapped s-line indices for axis 0, t-line indices for axis 1).
    """

    points: np.ndarray
    axis: np.ndarray
    extent: np.ndarray


@dataclass(frozen=True)
class SuitabilityReport:
    """Result of the analysis-suitability check.

    suitable : no s-extension meets a t-extension.
    junctions : all interior T-junctions and their extensions.
    pairs : (m, 2) int, indices into ``junctions`` of each offending
        (s-direction, t-direction) pair.
    pair_params : (m, 2, 2) float, the (s, t) knot values of both T-junctions.
    """

    suitable: bool
    junctions: TJunctions
    pairs: np.ndarray
    pair_params: np.ndarray

    def describe(self) -> str:
        """One line per offending pair (empty when suitable)."""
        return "\n".join(
            f"extension of T-junction (s={a[0]:.6g}, t={a[1]:.6g}) meets that of (s={b[0]:.6g}, t={b[1]:.6g})"
            for a, b in self.pair_params
        )


def t_junctions(mesh: TMesh) -> TJunctions:
    """Interior T-junctions of a mesh with their extensions."""
    left, right, down, up = mesh.edge_flags()
    s_n, t_n = mesh.shape
    # a vertex has edges both ways: an odd number of them is three
    tj = mesh.vertices & (left ^ right ^ down ^ up)
    tj[:, [0, t_n - 1]] = False
    if not mesh.periodic:
        tj[[0, s_n - 1], :] = False
    i, j = np.divmod(np.flatnonzero(tj), t_n)  # np.argwhere(tj), faster
    pts = np.stack([i, j], axis=1)
    axis = np.where(left[i, j] & right[i, j], 1, 0)
    s_idx, t_idx = mesh.knot_indices(pts) if len(pts) else (np.zeros((0, 5), int), np.zeros((0, 5), int))
    plus = np.where(axis == 0, ~right[i, j], ~up[i, j])  # missing edge points to +
    knots = np.where((axis == 0)[:, None], s_idx, t_idx)
    lo = np.where(plus, knots[:, 1], knots[:, 0])
    hi = np.where(plus, knots[:, 4], knots[:, 3])
    return TJunctions(pts, axis, np.stack([lo, hi], axis=1))


def check_suitability(mesh: TMesh) -> SuitabilityReport:
    """Check that no s-extension (along a t-line) meets a t-extension (along an s-line).

    Only the s-extensions on the rows a t-extension spans are tested against
    it (found by bisection in the s-extensions sorted by row).
    """
    tj = t_junctions(mesh)
    hs = np.flatnonzero(tj.axis == 0)
    vs = np.flatnonzero(tj.axis == 1)
    s_n = mesh.shape[0]
    # candidate pairs: each t-extension with the s-extensions on the rows it spans
    row = tj.points[hs, 1]
    by_row = np.argsort(row)
    first = np.searchsorted(row[by_row], tj.extent[vs, 0], side="left")
    count = np.searchsorted(row[by_row], tj.extent[vs, 1], side="right") - first
    vi = np.repeat(np.arange(len(vs)), count)
    hi = by_row[np.repeat(first - np.cumsum(count) + count, count) + np.arange(count.sum())]
    a, b = tj.extent[hs[hi], 0], tj.extent[hs[hi], 1]
    col = tj.points[vs[vi], 0]
    if mesh.periodic:
        col = a + np.mod(col - a, s_n)  # the copy of the column at or after a
    meet = (a <= col) & (col <= b)
    order = np.lexsort((vi[meet], hi[meet]))
    pairs = np.stack([hs[hi[meet][order]], vs[vi[meet][order]]], axis=1)
    params = np.stack(
        [mesh.s_value(tj.points[pairs, 0]), mesh.t_lines[tj.points[pairs, 1]]], axis=-1
    ).reshape(-1, 2, 2)
    return SuitabilityReport(len(pairs) == 0, tj, pairs, params)
