"""Local refinement (exact) and edge removal (least squares) of T-splines.

Refinement follows the blending-function refinement of Sederberg, Cardon,
Finnigan, North, Zheng, Lyche 2004 ("T-spline simplification and local
refinement", sec. 4) with the analysis-suitability closure of Scott, Li,
Sederberg, Hughes 2012 ("Local refinement of analysis-suitable T-splines",
CMAME 213-216):

1. insert the requested knot-line segments into the T-mesh (each end runs on
   to the nearest perpendicular edge, so the mesh stays valid);
2. extend T-junctions whose extensions meet, one face at a time, until the
   mesh is analysis-suitable; of each meeting pair the junction extended is
   the one whose step ends on a vertex (no new control point), else the one
   met behind itself (one step clears it), else the one in more pairs;
3. split every old blending function by Boehm knot insertion wherever the new
   mesh has a knot line crossing its s or t ray that the function lacks; the
   split-off pieces carry the old control points with the Boehm factors;
4. where a piece's anchor or knot is not in the mesh, add the edge (the mesh
   follows the function; one-sided where the point lies on a perpendicular
   edge already), and go back to 2.

When every piece is exactly a blending function of the final mesh, the pieces
that share an anchor are summed: new homogeneous control points = R @ old,
and the surface is unchanged up to rounding. Only functions whose support a
new line crosses are touched, so the number of control points grows locally.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal
from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp

from bonecad.errors import FitError, KernelError
from bonecad.splines.lsq import normal_equations, solve_spd
from bonecad.splines.tspline.basis import split_coefficients
from bonecad.splines.tspline.suitability import check_suitability
from bonecad.splines.tspline.tmesh import END_LINES, TMesh
from bonecad.splines.tspline.tspline import TSpline

#: Refinement closure rounds before giving up (each round only adds edges).
_MAX_ROUNDS = 10_000


@dataclass(frozen=True)
class KnotSegment:
    """A segment of a knot line to insert or remove.

    axis : "s" for a line of constant s (it runs in t), "t" for constant t.
    value : the line's knot value.
    lo, hi : where it starts and ends along the line (t for axis "s", s for
        axis "t"; for periodic s, hi may exceed the period's end, hi - lo <= period).
    """

    axis: Literal["s", "t"]
    value: float
    lo: float
    hi: float


@dataclass(frozen=True)
class Refinement:
    """Result of an exact refinement.

    tspline : the refined T-spline (same surface).
    matrix : csr (n_new, n_old): new [w P, w] = matrix @ old [w P, w].
    added : number of control points added in all.
    requested_vertices : vertices the requested segments alone created; the
        rest of ``added`` is what analysis-suitability and consistency needed.
    """

    tspline: TSpline
    matrix: sp.csr_matrix
    added: int
    requested_vertices: int


@dataclass(frozen=True)
class Removal:
    """Result of removing edges: the coarser T-spline closest to the old one.

    tspline : the T-spline on the coarser mesh (least squares in homogeneous space).
    max_deviation_mm : largest distance to the old surface at the check samples
        (rounding level when the old surface lies in the coarser space).
    """

    tspline: TSpline
    max_deviation_mm: float


# ---------------------------------------------------------------- edge editing
class _Edges:
    """Mutable copy of a mesh's edge arrays, for local edits during refinement."""

    def __init__(self, mesh: TMesh):
        self.mesh = mesh
        self.s_e = mesh.s_edges.copy()
        self.t_e = mesh.t_edges.copy()
        self.s_n, self.t_n = mesh.shape
        self.n_s_seg = self.s_e.shape[1]

    def snapshot(self) -> TMesh:
        m = self.mesh
        return TMesh(m.s_lines, m.t_lines, self.s_e.copy(), self.t_e.copy(), m.s_period)

    def _on_s(self, i: int, j: int) -> bool:
        """Grid point (i, j) touched by an edge running in s."""
        i %= self.s_n
        before = self.s_e[j, (i - 1) % self.n_s_seg] if (self.mesh.periodic or i > 0) else False
        after = self.s_e[j, i] if i < self.n_s_seg else False
        return bool(before or after)

    def _on_t(self, i: int, j: int) -> bool:
        i %= self.s_n
        return bool((j > 0 and self.t_e[i, j - 1]) or (j < self.t_n - 1 and self.t_e[i, j]))

    def add_s_line(self, i: int, a: int, b: int) -> None:
        """Edges on s-line i from t-line a to b (a < b), ends run on to s-edges."""
        i %= self.s_n
        self.t_e[i, a:b] = True
        while not self._on_s(i, a):
            a -= 1
            self.t_e[i, a] = True
        while not self._on_s(i, b):
            self.t_e[i, b] = True
            b += 1
        # an edge reaching a clamped boundary continues through the end strip
        if a == END_LINES - 1:
            self.t_e[i, :a] = True
        if b == self.t_n - END_LINES:
            self.t_e[i, b:] = True

    def add_t_line(self, j: int, a: int, b: int) -> None:
        """Edges on t-line j from s-line a to b (unwrapped, a < b), ends run on to t-edges."""
        self.s_e[j, np.arange(a, b) % self.n_s_seg] = True
        for _ in range(self.s_n + 1):
            if self._on_t(a, j):
                break
            a -= 1
            self.s_e[j, a % self.n_s_seg] = True
        for _ in range(self.s_n + 1):
            if self._on_t(b, j):
                break
            self.s_e[j, b % self.n_s_seg] = True
            b += 1
        if not self.mesh.periodic:
            if a == END_LINES - 1:
                self.s_e[j, :a] = True
            if b == self.s_n - END_LINES:
                self.s_e[j, b:] = True

    def _run_t(self, i: int, j: int, d: int) -> int:
        """From grid point (i, j) along s-line i in direction d: the next t-line with an s-edge there."""
        y = j + d
        while not self._on_s(i, y):
            y += d
        return y

    def _run_s(self, i: int, j: int, d: int) -> int:
        """From grid point (i, j) along t-line j in direction d: the next (unwrapped) s-line with a t-edge there."""
        x = i + d
        for _ in range(self.s_n + 1):
            if self._on_t(x, j):
                break
            x += d
        return x

    def cross_at(self, i: int, j: int, axis: str) -> None:
        """Make grid point (i, j) lie on a line of the given axis ("s": constant s).

        Where the point already lies on a perpendicular edge, one edge from it
        to the nearer perpendicular edge suffices (the side whose far end is
        a vertex already first): one vertex fewer than a crossing.
        """
        if axis == "s" and not self._on_t(i, j):
            if not self._on_s(i, j):
                self.add_s_line(i, j - 1, j + 1)
                return
            lo, hi = self._run_t(i, j, -1), self._run_t(i, j, 1)
            if (not self._on_t(i, hi), hi - j) <= (not self._on_t(i, lo), j - lo):
                self.add_s_line(i, j, hi)
            else:
                self.add_s_line(i, lo, j)
        elif axis == "t" and not self._on_s(i, j):
            if not self._on_t(i, j):
                self.add_t_line(j, i - 1, i + 1)
                return
            lo, hi = self._run_s(i, j, -1), self._run_s(i, j, 1)
            if (not self._on_s(hi, j), hi - i) <= (not self._on_s(lo, j), i - lo):
                self.add_t_line(j, i, hi)
            else:
                self.add_t_line(j, lo, i)


# ------------------------------------------------------------------- closure
def _step(edges: _Edges, right, up, i: int, j: int, axis: int) -> tuple[tuple[int, int], bool]:
    """One-face extension of a T-junction at (i, j): (grid step to add, whether
    the line it runs on to is met at a vertex already, so that it costs none)."""
    if axis == 0:
        d = -1 if right[i, j] else 1
        x = edges._run_s(i, j, d)
        return ((i, i + 1) if d > 0 else (i - 1, i)), edges._on_s(x, j)
    d = -1 if up[i, j] else 1
    y = edges._run_t(i, j, d)
    return ((j, j + 1) if d > 0 else (j - 1, j)), edges._on_t(i, y)


def _cover(pairs: np.ndarray, free: np.ndarray, behind: np.ndarray) -> list[int]:
    """T-junctions to extend so that each offending pair has one of them.

    A greedy vertex cover: per pair, the junction whose extension step costs
    no vertex (it ends on a vertex), else the one that meets the other's
    extension behind itself (one step forward clears that; a meeting ahead
    needs two or more), else the junction in more pairs, else the s-direction one.
    behind : (m, 2) bool per pair and member.
    """
    degree = np.bincount(pairs.ravel(), minlength=len(free))
    chosen: set[int] = set()
    for (h, v), (bh, bv) in zip(pairs.tolist(), behind.tolist()):
        if h not in chosen and v not in chosen:
            chosen.add(v if (free[v], bv, degree[v]) > (free[h], bh, degree[h]) else h)
    return sorted(chosen)


def _make_suitable(edges: _Edges) -> TMesh:
    """Extend T-junctions with meeting extensions until the mesh is analysis-suitable."""
    for _ in range(_MAX_ROUNDS):
        mesh = edges.snapshot()
        report = check_suitability(mesh)
        if report.suitable:
            return mesh
        tj = report.junctions
        _, right, _, up = mesh.edge_flags()
        steps = {}
        free = np.zeros(len(tj.points), dtype=bool)
        for k in np.unique(report.pairs).tolist():
            i, j = tj.points[k].tolist()
            steps[k], free[k] = _step(edges, right, up, i, j, int(tj.axis[k]))
        # where each pair meets, relative to each junction's direction of extension
        h, v = report.pairs[:, 0], report.pairs[:, 1]
        d_s = tj.points[v, 0] - tj.points[h, 0]
        if mesh.periodic:
            d_s = np.mod(d_s + edges.s_n // 2, edges.s_n) - edges.s_n // 2
        d_t = tj.points[h, 1] - tj.points[v, 1]
        dir_h = np.where(right[tj.points[h, 0], tj.points[h, 1]], -1, 1)
        dir_v = np.where(up[tj.points[v, 0], tj.points[v, 1]], -1, 1)
        behind = np.stack([d_s * dir_h < 0, d_t * dir_v < 0], axis=1)
        for k in _cover(report.pairs, free, behind):
            i, j = tj.points[k]
            if tj.axis[k] == 0:
                edges.add_t_line(j, *steps[k])
            else:
                edges.add_s_line(i, *steps[k])
    raise KernelError("refinement: analysis-suitability closure did not converge")


def _keys(s_idx: np.ndarray, t_idx: np.ndarray) -> list[bytes]:
    """Hashable keys of blending functions: the bytes of their 10 knot indices
    (cheaper to build and hash than tuples)."""
    rows = np.concatenate([s_idx, t_idx], axis=1).astype(np.int64, copy=False)
    return rows.view("V80").ravel().tolist()


def _knots(keys: list[bytes]) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of ``_keys``: (n, 5) s and (n, 5) t knot indices."""
    rows = np.frombuffer(b"".join(keys), dtype=np.int64).reshape(-1, 10)
    return rows[:, :5], rows[:, 5:]


def _normalised(s_idx: np.ndarray, s_n: int, periodic: bool) -> np.ndarray:
    """Shift unwrapped s indices so each anchor's s-line lies in 0..S-1."""
    if not periodic:
        return s_idx
    return s_idx - (s_idx[:, 2:3] // s_n) * s_n


def _next_crossings(cross: np.ndarray, periodic: bool) -> np.ndarray:
    """(R, L) int: per row and line x, the first line after x that crosses the
    row (unwrapped past L when periodic; L or more when there is none)."""
    n = cross.shape[1]
    at_or_after = np.minimum.accumulate(np.where(cross, np.arange(n), n)[:, ::-1], axis=1)[:, ::-1]
    after = np.hstack([at_or_after[:, 1:], np.full((len(cross), 1), n)])
    if periodic:
        after = np.where(after == n, at_or_after[:, :1] + n, after)
    return after


def _first_missing(knots: np.ndarray, after: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per knot vector, the smallest line crossing its ray strictly inside
    (knots[0], knots[4]) that is not one of its knots.

    knots : (n, 5) int (unwrapped indices in a periodic row); after : the
    rows' ``_next_crossings``; rows : (n,) the row of each ray.
    Returns (n,) gap (the line goes between knots[gap] and knots[gap + 1];
    -1 where none is missing) and (n,) the line (unwrapped).
    """
    n = after.shape[1]
    base = knots[:, :4] // n * n
    nxt = after[rows[:, None], knots[:, :4] - base] + base
    inside = nxt < knots[:, 1:]
    gap = np.where(inside.any(axis=1), inside.argmax(axis=1), -1)
    return gap, nxt[np.arange(len(knots)), np.maximum(gap, 0)]


def _split_table(mesh: TMesh, keys: list[bytes]) -> dict:
    """The Boehm splits the mesh's rays demand, for ``keys`` and all they split into.

    Per key: () when no knot is missing, else ((first part, c1), (second
    part, c2)) for the first missing knot, s before t, smallest first.
    """
    s_n = mesh.shape[0]
    after_s = _next_crossings(mesh.on_t.T, mesh.periodic)  # per t-line: s-lines crossing it
    after_t = _next_crossings(mesh.on_s, False)  # per s-line: t-lines crossing it
    table: dict = {}
    todo = list(set(keys))
    while todo:
        sv, tv = _knots(todo)
        gap_s, k_s = _first_missing(sv, after_s, tv[:, 2])
        gap_t, k_t = _first_missing(tv, after_t, sv[:, 2])
        in_s = np.flatnonzero(gap_s >= 0)
        in_t = np.flatnonzero((gap_s < 0) & (gap_t >= 0))
        table.update(dict.fromkeys(todo, ()))
        children = []
        for axis, idx in enumerate((in_s, in_t)):
            knots = [sv[idx], tv[idx]]
            old, k = knots[axis], (k_s, k_t)[axis][idx]
            value = (mesh.s_value, mesh.t_value)[axis]
            c1, c2 = split_coefficients(value(old), value(k))
            six = np.sort(np.concatenate([old, k[:, None]], axis=1), axis=1)
            halves = []
            for part in (six[:, :5], six[:, 1:]):  # first and last five
                knots[axis] = part
                halves.append(_keys(_normalised(knots[0], s_n, mesh.periodic), knots[1]))
            parents = [todo[i] for i in idx.tolist()]
            table.update(zip(parents, zip(zip(halves[0], c1.tolist()), zip(halves[1], c2.tolist()))))
            children += halves[0] + halves[1]
        todo = list({k for k in children if k not in table})
    return table


def _split_pieces(mesh: TMesh, pieces: dict, todo: list) -> None:
    """Split pieces by Boehm insertion of every knot the mesh's rays demand.

    Depth first from the end of ``todo``; a part that is a piece already
    adds into it. The splits come from ``_split_table``; this order fixes the
    rounding of the sums.
    """
    table = _split_table(mesh, todo)
    todo = [key for key in todo if table[key]]
    while todo:
        key = todo.pop()
        coef = pieces.pop(key, None)
        if coef is None:
            continue
        for part, c in table[key]:
            target = pieces.setdefault(part, {})
            for a, v in coef.items():
                target[a] = target.get(a, 0.0) + c * v
            if table[part]:
                todo.append(part)


def _close(edges: _Edges, pieces: dict) -> tuple[TMesh, list[bytes]]:
    """Grow the mesh and split the pieces until both agree (see module docstring).

    Returns the mesh and its anchors' keys.
    """
    for _ in range(_MAX_ROUNDS):
        mesh = _make_suitable(edges)
        anchors = _keys(*mesh.anchor_knots)
        anchor_set = set(anchors)
        _split_pieces(mesh, pieces, [k for k in pieces if k not in anchor_set])
        stray = [k for k in pieces if k not in anchor_set]
        if not stray:
            if len(anchor_set) != len(pieces):
                raise KernelError(
                    f"refinement: {len(anchor_set) - len(pieces)} new control point(s) received no "
                    "contribution (the spline spaces are not nested)"
                )
            return mesh, anchors
        # per stray and knot m, in this order: the point of its m-th s-knot on
        # its t-line must lie on an s-line, that of its m-th t-knot on its
        # s-line on a t-line; points that do already stay so (edges are only added)
        sv, tv = _knots(stray)
        i = np.stack([sv, np.repeat(sv[:, 2:3], 5, axis=1)], axis=2) % mesh.shape[0]
        j = np.stack([np.repeat(tv[:, 2:3], 5, axis=1), tv], axis=2)
        axis = np.broadcast_to(np.array(["s", "t"]), i.shape)
        add = ~np.where(axis == "s", mesh.on_t[i, j], mesh.on_s[i, j])
        for p, q, a in zip(i[add].tolist(), j[add].tolist(), axis[add].tolist()):
            edges.cross_at(p, q, a)
    raise KernelError("refinement: did not converge")


# ------------------------------------------------------------------ public API
def insert_segments(ts: TSpline, segments: Sequence[KnotSegment], *, tol: float | None = None) -> Refinement:
    """Insert knot-line segments; exact, analysis-suitable local refinement.

    segments : where to add knot lines; values not yet knots become new
        lines of the grid; segment ends snap outward to existing lines and run
        on to the nearest perpendicular edge.
    tol : knot values closer than this are one line (default 1e-12 of the
        parameter domain size).
    """
    mesh = ts.mesh
    if tol is None:
        size = max(np.ptp(mesh.t_lines), mesh.s_range[1] - mesh.s_range[0])
        tol = 1e-12 * size
    s_map = np.arange(mesh.shape[0])
    t_map = np.arange(mesh.shape[1])
    for seg in segments:
        if seg.axis not in ("s", "t"):
            raise ValueError(f"KnotSegment.axis: expected 's' or 't', got {seg.axis!r}")
        if not seg.hi > seg.lo:
            raise ValueError(f"KnotSegment: expected lo < hi, got lo={seg.lo}, hi={seg.hi}")
        mesh, k, is_new = mesh.with_line(seg.axis, seg.value, tol)
        if is_new:
            m = s_map if seg.axis == "s" else t_map
            m[m >= k] += 1
    # each segment's line in the final grid (later insertions shift indices)
    lines = [mesh.with_line(seg.axis, seg.value, tol)[1] for seg in segments]
    edges = _Edges(mesh)
    s_n = mesh.shape[0]
    for seg, k in zip(segments, lines):
        if seg.axis == "s":
            a, b = _snap(mesh.t_lines, seg.lo, seg.hi, tol)
            edges.add_s_line(k, a, b)
        else:
            a, b = _snap_s(mesh, seg.lo, seg.hi, tol)
            edges.add_t_line(k, a, b)
    requested = int(edges.snapshot().vertices.sum() - mesh.vertices.sum())

    old_s, old_t = ts.mesh.anchor_knots
    old_sn = ts.mesh.shape[0]
    new_s = s_map[old_s % old_sn] + np.floor_divide(old_s, old_sn) * s_n
    new_t = t_map[old_t]
    pieces = {key: {n: 1.0} for n, key in enumerate(_keys(_normalised(new_s, s_n, mesh.periodic), new_t))}
    final, anchors = _close(edges, pieces)
    final.validate()
    coefs = [pieces[key] for key in anchors]
    rows = np.repeat(np.arange(len(coefs)), [len(c) for c in coefs])
    cols = [a for c in coefs for a in c]
    vals = [v for c in coefs for v in c.values()]
    n_new = len(final.anchors)
    matrix = sp.csr_matrix((vals, (rows, cols)), shape=(n_new, ts.n_control))
    if ts.polynomial:  # the rows sum to 1: a polynomial T-spline stays one (weights exactly 1, not 1 - 1e-16)
        new = TSpline(final, matrix @ ts.control_points, np.ones(n_new))
    else:
        pw = matrix @ np.hstack([ts.control_points * ts.weights[:, None], ts.weights[:, None]])
        new = TSpline(final, pw[:, :3] / pw[:, 3:], pw[:, 3])
    return Refinement(new, matrix, n_new - ts.n_control, requested)


def refine_elements(ts: TSpline, elements: Sequence[int] | np.ndarray, axes: np.ndarray | None = None) -> Refinement:
    """Split Bezier elements at their parametric midlines (exact).

    axes : optional (n, 2) bool per element, [halve in s (insert its s-midline),
        halve in t]; default both (each element into four). An element with
        neither is left alone.
    """
    ext = ts.extraction
    e = np.asarray(elements, dtype=np.int64).ravel()
    if e.size and (e.min() < 0 or e.max() >= ext.n_elements):
        raise ValueError(f"elements: indices must lie in 0..{ext.n_elements - 1}")
    split = np.ones((e.size, 2), dtype=bool) if axes is None else np.asarray(axes, dtype=bool)
    if split.shape != (e.size, 2):
        raise ValueError(f"axes: expected ({e.size}, 2) bool, got {split.shape}")
    sb, tb = ext.s_bounds[e], ext.t_bounds[e]
    segs = []
    for (s0, s1), (t0, t1), (in_s, in_t) in zip(sb.tolist(), tb.tolist(), split.tolist()):
        if in_s:
            segs.append(KnotSegment("s", 0.5 * (s0 + s1), t0, t1))
        if in_t:
            segs.append(KnotSegment("t", 0.5 * (t0 + t1), s0, s1))
    return insert_segments(ts, segs)


def _snap(lines: np.ndarray, lo: float, hi: float, tol: float) -> tuple[int, int]:
    """Clamped direction: line indices at or outside [lo, hi] (real lines only)."""
    real = np.arange(3, len(lines) - 3)
    a = real[lines[real] <= lo + tol]
    b = real[lines[real] >= hi - tol]
    if a.size == 0 or b.size == 0:
        raise ValueError(f"segment [{lo}, {hi}] leaves the parameter range [{lines[0]}, {lines[-1]}]")
    return int(a[-1]), int(b[0])


def _snap_s(mesh: TMesh, lo: float, hi: float, tol: float) -> tuple[int, int]:
    """s-range to (unwrapped) s-line indices at or outside it."""
    if mesh.s_period is None:
        return _snap(mesh.s_lines, lo, hi, tol)
    s_n = mesh.shape[0]
    if hi - lo > mesh.s_period + tol:
        raise ValueError(f"segment [{lo}, {hi}] is longer than the s period {mesh.s_period}")
    base = mesh.s_lines[0]
    lo_w = base + np.mod(lo - base, mesh.s_period)
    a = int(np.searchsorted(mesh.s_lines, lo_w + tol, side="right") - 1)
    s_a = mesh.s_value(a)
    end = s_a + (hi - lo) + (lo_w - s_a)
    cand = np.arange(a + 1, a + s_n + 1)
    b = int(cand[np.searchsorted(mesh.s_value(cand), end - tol)])
    return a, b


def remove_segments(ts: TSpline, segments: Sequence[KnotSegment], *, samples_per_element: int = 6) -> Removal:
    """Remove T-mesh edges along knot-line segments and refit the surface.

    Removes every unit edge on the segments' lines between lo and hi. The
    coarser mesh must be valid and analysis-suitable (else ValueError naming
    the reason). The new control points minimise the squared distance of the
    homogeneous surfaces at ``samples_per_element``^2 points per new element,
    so the surface is kept exactly when it lies in the coarser space (rows
    that end in T-points over a region where the rows agree).
    """
    mesh = ts.mesh
    tol = 1e-12 * max(np.ptp(mesh.t_lines), mesh.s_range[1] - mesh.s_range[0])
    s_e, t_e = mesh.s_edges.copy(), mesh.t_edges.copy()
    for seg in segments:
        if seg.axis == "s":
            hit = np.flatnonzero(np.abs(mesh.s_lines - seg.value) <= tol)
            if hit.size == 0:
                raise ValueError(f"remove: s = {seg.value} is not a knot line")
            a, b = _snap(mesh.t_lines, seg.lo, seg.hi, tol)
            t_e[hit[0], a:b] = False
        else:
            hit = np.flatnonzero(np.abs(mesh.t_lines[3:-3] - seg.value) <= tol) + 3
            if hit.size == 0:
                raise ValueError(f"remove: t = {seg.value} is not a knot line")
            a, b = _snap_s(mesh, seg.lo, seg.hi, tol)
            s_e[hit[0], np.arange(a, b) % s_e.shape[1]] = False
    coarse = mesh.with_edges(s_e, t_e)
    report = check_suitability(coarse)
    if not report.suitable:
        raise ValueError("remove: the coarser T-mesh is not analysis-suitable:\n" + report.describe())
    shape = TSpline(coarse, np.zeros((len(coarse.anchors), 3)), np.ones(len(coarse.anchors)))
    ext = shape.extraction
    g = (np.arange(samples_per_element) + 0.5) / samples_per_element
    uu, vv = np.meshgrid(g, g, indexing="ij")
    s = ext.s_bounds[:, :1] + uu.ravel()[None, :] * np.diff(ext.s_bounds, axis=1)
    t = ext.t_bounds[:, :1] + vv.ravel()[None, :] * np.diff(ext.t_bounds, axis=1)
    s, t = s.ravel(), t.ravel()
    basis = shape.basis_matrix(s, t)  # polynomial blending functions (weights 1)
    old_shape = TSpline(mesh, np.zeros((ts.n_control, 3)), np.ones(ts.n_control))
    target = old_shape.basis_matrix(s, t) @ np.hstack([ts.control_points * ts.weights[:, None], ts.weights[:, None]])
    pw = solve_spd(*normal_equations(basis, np.ones(len(s)), target))
    if np.any(pw[:, 3] <= 0):
        raise FitError("remove: the refitted weights are not all positive")
    new = TSpline(coarse, pw[:, :3] / pw[:, 3:], pw[:, 3])
    dev = np.linalg.norm(new.evaluate(s, t).points - ts.evaluate(s, t).points, axis=1)
    return Removal(new, float(dev.max()))

