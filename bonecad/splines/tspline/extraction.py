"""Bezier extraction of a cubic T-spline (Scott, Borden, Verhoosel, Sederberg,
Hughes 2011, "Isogeometric finite element data structures based on Bezier
extraction of T-splines", IJNME 88).

Elements are the faces of the *Bezier mesh*: the T-mesh together with every
knot line of every blending function inside its support (for an
analysis-suitable T-mesh, the T-mesh plus its T-junction extensions). On each
element every blending function is one bicubic polynomial; its Bernstein
coefficients are that function's row of the element's extraction operator
C_e, and the element's homogeneous Bezier control points are
C_e^T [w P, w].

The operator of all elements is kept as one sparse matrix (16 n_e x n_A), row
16 e + 4 a + b for Bernstein B_a(u) B_b(v) of element e, so that
homogeneous Bezier points = operator @ [w P, w].
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from bonecad.splines.basis import find_span
from bonecad.splines.tspline.basis import bezier_coefficients
from bonecad.splines.tspline.tmesh import END_LINES, TMesh


@dataclass(frozen=True, eq=False)
class BezierExtraction:
    """Elements and extraction operators of one T-mesh (no geometry).

    index_bounds : (n_e, 4) int, [i0, i1, j0, j1]: element spans s-lines i0..i1
        (i0 in 0..S-1; i1 > i0, unwrapped when s is periodic) and t-lines j0..j1.
    s_bounds, t_bounds : (n_e, 2) float, parameter bounds of each element
        (s_bounds[:, 1] may exceed the period's end for an element across the seam).
    cell_element : (Ns, T - 1) int, element of each grid cell, -1 for the
        zero-width cells of the clamped end strips.
    pair_ptr : (n_e + 1,) int; the blending functions on element e are
        pair_anchor[pair_ptr[e]:pair_ptr[e + 1]].
    pair_anchor : (n_pairs,) int, anchor index of each (element, function) pair.
    pair_coef : (n_pairs, 16) float, Bernstein coefficients (row of C_e), index 4 a + b.
    """

    mesh: TMesh
    index_bounds: np.ndarray
    s_bounds: np.ndarray
    t_bounds: np.ndarray
    cell_element: np.ndarray
    pair_ptr: np.ndarray
    pair_anchor: np.ndarray
    pair_coef: np.ndarray

    @property
    def n_elements(self) -> int:
        """Number of Bezier elements."""
        return len(self.index_bounds)

    @cached_property
    def operator(self) -> sp.csr_matrix:
        """(16 n_e, n_A) sparse extraction operator (all elements stacked); built once per extraction (a fit
        re-solves, and a shape model evaluates, many control-point sets on one T-mesh)."""
        n_e, n_a = self.n_elements, len(self.mesh.anchors)
        elem = np.repeat(np.arange(n_e), np.diff(self.pair_ptr))
        rows = (16 * elem[:, None] + np.arange(16)).ravel()
        cols = np.repeat(self.pair_anchor, 16)
        return sp.csr_matrix((self.pair_coef.ravel(), (rows, cols)), shape=(16 * n_e, n_a))

    def element_operator(self, e: int) -> tuple[np.ndarray, np.ndarray]:
        """Extraction operator of one element: (anchor indices (k,), C_e (k, 16))."""
        sl = slice(self.pair_ptr[e], self.pair_ptr[e + 1])
        return self.pair_anchor[sl], self.pair_coef[sl]

    def locate(self, s: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Element and local Bezier coordinates of parameter points.

        s, t : (n,) float. s wraps when periodic; points outside the
        parameter range by more than 1e-9 of its size raise ValueError.
        Returns (element (n,) int, u (n,) float in [0, 1], v (n,) float in [0, 1]).
        """
        mesh = self.mesh
        s = np.asarray(s, dtype=np.float64).ravel()
        t = np.asarray(t, dtype=np.float64).ravel()
        if s.shape != t.shape:
            raise ValueError(f"s and t: expected equal lengths, got {s.size} and {t.size}")
        t = _clamp(t, *mesh.t_range, "t")
        j = find_span(mesh.t_lines, t, END_LINES - 1)  # the end lines act as clamped knots
        if mesh.s_period is not None:
            lo = mesh.s_lines[0]
            s = lo + np.mod(s - lo, mesh.s_period)
            i = np.clip(find_span(mesh.s_lines, s), 0, len(mesh.s_lines) - 1)
        else:
            s = _clamp(s, *mesh.s_range, "s")
            i = find_span(mesh.s_lines, s, END_LINES - 1)
        e = self.cell_element[i, j]
        ds = s - self.s_bounds[e, 0]
        if mesh.periodic:
            ds = np.where(ds < 0, ds + mesh.s_period, ds)
        u = ds / (self.s_bounds[e, 1] - self.s_bounds[e, 0])
        v = (t - self.t_bounds[e, 0]) / (self.t_bounds[e, 1] - self.t_bounds[e, 0])
        return e, u, v


def _clamp(x: np.ndarray, lo: float, hi: float, name: str) -> np.ndarray:
    tol = 1e-9 * max(hi - lo, 1.0)
    bad = (x < lo - tol) | (x > hi + tol) | ~np.isfinite(x)
    if bad.any():
        raise ValueError(f"{name}: {int(bad.sum())} value(s) outside the parameter range [{lo}, {hi}], "
                         f"e.g. {x[bad][0]}")
    return np.clip(x, lo, hi)


def bezier_mesh_edges(mesh: TMesh) -> tuple[np.ndarray, np.ndarray]:
    """Edges of the Bezier mesh: T-mesh edges plus every blending function's knot lines.

    Returns (s_edges, t_edges) with the shapes of the mesh's edge arrays.
    """
    s_n, t_n = mesh.shape
    s_idx, t_idx = mesh.anchor_knots
    # knot lines of constant s: from t_idx[:, 0] to t_idx[:, 4]
    diff = np.zeros((s_n, t_n + 1), dtype=np.int64)
    cols = (s_idx % s_n).ravel()
    np.add.at(diff, (cols, np.repeat(t_idx[:, 0], 5)), 1)
    np.add.at(diff, (cols, np.repeat(t_idx[:, 4], 5)), -1)
    t_edges = mesh.t_edges | (np.cumsum(diff, axis=1)[:, : t_n - 1] > 0)
    # knot lines of constant t: from s_idx[:, 0] to s_idx[:, 4] (unwrapped)
    a, b = s_idx[:, 0], s_idx[:, 4]
    if mesh.periodic:
        shift = np.floor_divide(a, s_n) * s_n
        a, b = a - shift, b - shift
        width = 2 * s_n
    else:
        width = s_n - 1
    diff = np.zeros((t_n, width + 1), dtype=np.int64)
    rows = t_idx.ravel()
    np.add.at(diff, (rows, np.repeat(a, 5)), 1)
    np.add.at(diff, (rows, np.repeat(b, 5)), -1)
    cover = np.cumsum(diff, axis=1)[:, :width] > 0
    if mesh.periodic:
        cover = cover[:, :s_n] | cover[:, s_n:]
    return mesh.s_edges | cover, t_edges


def _last_at_or_before(mask: np.ndarray, periodic: bool) -> np.ndarray:
    """Per position along axis 0: index of the last True at or before it (unwrapped)."""
    n = mask.shape[0]
    idx = np.where(mask, np.arange(n)[:, None], -1)
    acc = np.maximum.accumulate(idx, axis=0)
    if periodic:
        acc = np.where(acc < 0, acc[-1][None, :] - n, acc)
    return acc


def _next_after(mask: np.ndarray, periodic: bool) -> np.ndarray:
    """Per position along axis 0: index of the first True strictly after it (unwrapped)."""
    n = mask.shape[0]
    big = np.iinfo(np.int64).max // 4
    idx = np.where(mask, np.arange(n)[:, None], big)
    acc = np.minimum.accumulate(idx[::-1], axis=0)[::-1]
    nxt = np.vstack([acc[1:], np.full((1, mask.shape[1]), big)])
    if periodic:
        nxt = np.where(nxt >= big, acc[0][None, :] + n, nxt)
    return nxt


def extract(mesh: TMesh) -> BezierExtraction:
    """Bezier elements and extraction operators of a T-mesh (vectorised)."""
    s_n, t_n = mesh.shape
    periodic = mesh.periodic
    n_s_cells = s_n if periodic else s_n - 1
    ext_s, ext_t = bezier_mesh_edges(mesh)

    s_len = np.diff(mesh.s_value(np.arange(n_s_cells + 1)))
    t_len = np.diff(mesh.t_lines)
    real = (s_len > 0)[:, None] & (t_len > 0)[None, :]  # (Ns, T-1)

    # lower-left cell of the face holding each cell
    left = _last_at_or_before(ext_t[:n_s_cells], periodic)  # (Ns, T-1) s-line
    left_mod = left % n_s_cells
    below_all = _last_at_or_before(ext_s[: t_n - 1], False).T  # (Ns, T-1) t-line
    jj = np.broadcast_to(np.arange(t_n - 1), real.shape)
    bottom = below_all[left_mod, jj]
    key = left_mod * t_n + bottom
    keys, cell_e = np.unique(key[real], return_inverse=True)
    cell_element = np.full(real.shape, -1, dtype=np.int64)
    cell_element[real] = cell_e
    i0, j0 = keys // t_n, keys % t_n
    right_next = _next_after(ext_t, periodic)  # (S, T-1) next s-line
    up_next = _next_after(ext_s, False)  # (T, Ns) next t-line
    i1 = right_next[i0, j0]
    j1 = up_next[j0, i0]
    n_e = len(keys)
    area = (i1 - i0) * (j1 - j0)
    if np.any(np.bincount(cell_e, minlength=n_e) != area):
        raise ValueError("invalid T-mesh: its Bezier mesh has non-rectangular faces")
    index_bounds = np.stack([i0, i1, j0, j1], axis=1)
    s_bounds = np.stack([mesh.s_value(i0), mesh.s_value(i1)], axis=1)
    t_bounds = np.stack([mesh.t_lines[j0], mesh.t_lines[j1]], axis=1)

    pair_elem, pair_anchor = _support_pairs(mesh, cell_element, n_s_cells)
    pair_ptr = np.concatenate([[0], np.cumsum(np.bincount(pair_elem, minlength=n_e))])

    s_idx, t_idx = mesh.anchor_knots
    ks, kt = s_idx[pair_anchor], t_idx[pair_anchor]
    e0 = i0[pair_elem]
    if periodic:
        e0 = e0 + s_n * -np.floor_divide(e0 - ks[:, 0], s_n)  # unwrap into the support
    e1 = e0 + (i1 - i0)[pair_elem]
    cs = bezier_coefficients(mesh.s_value(ks), mesh.s_value(e0), mesh.s_value(e1))
    ct = bezier_coefficients(mesh.t_lines[kt], t_bounds[pair_elem, 0], t_bounds[pair_elem, 1])
    pair_coef = (cs[:, :, None] * ct[:, None, :]).reshape(-1, 16)
    return BezierExtraction(mesh, index_bounds, s_bounds, t_bounds, cell_element, pair_ptr, pair_anchor, pair_coef)


def _support_pairs(mesh: TMesh, cell_element: np.ndarray, n_s_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """All (element, anchor) pairs with the element inside the anchor's support.

    Returns (element (n_pairs,), anchor (n_pairs,)) sorted by element, then anchor.
    """
    s_idx, t_idx = mesh.anchor_knots
    w = s_idx[:, 4] - s_idx[:, 0]
    h = t_idx[:, 4] - t_idx[:, 0]
    cells = w * h
    anchor = np.repeat(np.arange(len(w)), cells)
    start = np.concatenate([[0], np.cumsum(cells)[:-1]])
    local = np.arange(int(cells.sum())) - np.repeat(start, cells)
    wr = w[anchor]
    ci = (s_idx[anchor, 0] + local % wr) % n_s_cells
    cj = t_idx[anchor, 0] + local // wr
    elem = cell_element[ci, cj]
    keep = elem >= 0
    n_a = len(w)
    key = np.unique(elem[keep] * n_a + anchor[keep])
    return key // n_a, key % n_a
