"""The T-mesh: topology in integer index space, knot values on the side.

Index space. All knot lines of the mesh form a global grid: s-lines (constant
s) with indices 0..S-1 and t-lines (constant t) with indices 0..T-1. The
T-mesh is the set of unit edges of that grid it uses:

- ``s_edges[j, i]``: the edge on t-line j from s-line i to s-line i+1 (it runs
  in s); the last column wraps from S-1 to 0 when s is periodic.
- ``t_edges[i, j]``: the edge on s-line i from t-line j to t-line j+1.

A grid point is a *vertex* when edges of both directions touch it; a vertex
with three edges is a T-junction. Lines of the grid that carry no edge at a
point do not make it a vertex, so the grid may be much finer than the mesh
locally.

Open (clamped) directions carry four lines at each end with the boundary knot
value (zero knot intervals, Scott et al. 2011, sec. 3): indices 0-1 and n-2..n-1
are phantom lines without control points, lines 2-3 and n-4..n-3 hold the two
boundary rows of control points. Those strips are always complete. A periodic
direction has no phantoms: line indices wrap, and knot values unwrap by the
period (an index i + m*S stands for value lines[i] + m*period).

Anchors (control points) are the vertices off the phantom lines, ordered by
t-line, then s-line. Their local knot vectors come from ray casting
(Sederberg et al. 2003, sec. 3): the two nearest crossings of perpendicular
edges on each side along the anchor's own lines.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np


#: Phantom lines at each open end that carry no control points (cubic: 2).
PHANTOM = 2
#: Lines at each open end that share the boundary knot value (cubic: 4).
END_LINES = 4


def _before(edges: np.ndarray) -> np.ndarray:
    """Periodic rows: per grid point, the edge that ends at it (np.roll by 1, faster)."""
    return np.concatenate([edges[:, -1:], edges[:, :-1]], axis=1)


def _touch(edges: np.ndarray, periodic: bool) -> np.ndarray:
    """Which grid points each row's edges touch (cover or end at).

    edges : (rows, segments) bool. Returns (rows, lines) bool.
    """
    if periodic:
        return edges | _before(edges)
    out = np.zeros((edges.shape[0], edges.shape[1] + 1), dtype=bool)
    out[:, :-1] |= edges
    out[:, 1:] |= edges
    return out


def _neighbour_flags(edges: np.ndarray, periodic: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per grid point: is there an edge before it, and one after it, along the row.

    edges : (rows, segments) bool. Returns two (rows, lines) bool arrays.
    """
    if periodic:
        return _before(edges), edges.copy()
    rows = edges.shape[0]
    pad = np.zeros((rows, 1), dtype=bool)
    return np.hstack([pad, edges]), np.hstack([edges, pad])


def ray_cast(cross: np.ndarray, rows: np.ndarray, pos: np.ndarray, periodic: bool) -> np.ndarray:
    """Local knot indices by ray casting along the rows of a crossing mask.

    cross : (R, L) bool, cross[r, l] when line l crosses (or touches) row r.
    rows, pos : (n,) int, the points to cast from; cross[rows, pos] must hold.
    periodic : whether rows wrap (indices then unwrap: l + m*L).

    Returns (n, 5) int: the indices [l-2, l-1, l, l+1, l+2] of crossings.
    Raises ValueError when a ray leaves an open row or wraps over itself.
    """
    n_rows, n_lines = cross.shape
    flat = np.flatnonzero(cross)  # r * n_lines + l, row by row (faster than 2-D nonzero)
    l_idx = flat % n_lines
    ptr = np.searchsorted(flat, np.arange(n_rows + 1) * n_lines)
    counts = np.diff(ptr)
    loc = np.searchsorted(flat, rows * n_lines + pos)
    p = loc - ptr[rows]
    c = counts[rows][:, None]
    q = p[:, None] + np.arange(-2, 3)
    if periodic:
        wrap = np.floor_divide(q, np.maximum(c, 1))
        idx = l_idx[ptr[rows][:, None] + q - wrap * c] + wrap * n_lines
        bad = np.flatnonzero(c[:, 0] < 4)
        if bad.size:
            raise ValueError(
                f"{bad.size} ray(s) wrap over themselves: a periodic row needs at least 4 "
                f"crossing lines, row {rows[bad[0]]} has {c[bad[0], 0]}"
            )
        return idx
    bad = np.flatnonzero((q[:, 0] < 0) | (q[:, 4] >= c[:, 0]))
    if bad.size:
        raise ValueError(
            f"{bad.size} ray(s) leave the domain: point at line {pos[bad[0]]} of row "
            f"{rows[bad[0]]} lacks two crossings on a side"
        )
    return l_idx[ptr[rows][:, None] + q]


@dataclass(frozen=True, eq=False)
class TMesh:
    """A cubic T-mesh on a global grid of knot lines (see the module docstring).

    s_lines : (S,) float, s knot value of each s-line (open: 4 equal values at
        each end; periodic: strictly increasing within one period).
    t_lines : (T,) float, t knot value of each t-line (open, 4 equal at each end).
    s_edges : (T, S) bool if s is periodic, else (T, S - 1).
    t_edges : (S, T - 1) bool.
    s_period : float or None; the period of s (None: s is open too).
    """

    s_lines: np.ndarray
    t_lines: np.ndarray
    s_edges: np.ndarray
    t_edges: np.ndarray
    s_period: float | None = None

    # ------------------------------------------------------------------ build
    @classmethod
    def grid(cls, s_knots, t_knots, *, s_period: float | None = None) -> TMesh:
        """A tensor-product T-mesh (every line complete).

        s_knots : (m,) distinct s knot values. Periodic (s_period given): the m
            knots of one period, in [s_knots[0], s_knots[0] + s_period).
            Open: the m distinct knots of a clamped knot vector (ends included).
        t_knots : (k,) distinct t knot values, ends included (clamped).
        """
        s = np.asarray(s_knots, dtype=np.float64)
        t = np.asarray(t_knots, dtype=np.float64)
        s_lines = s if s_period is not None else _clamped_lines(s, "s_knots")
        t_lines = _clamped_lines(t, "t_knots")
        n_s_seg = len(s_lines) if s_period is not None else len(s_lines) - 1
        mesh = cls(
            s_lines=s_lines.copy(),
            t_lines=t_lines,
            s_edges=np.ones((len(t_lines), n_s_seg), dtype=bool),
            t_edges=np.ones((len(s_lines), len(t_lines) - 1), dtype=bool),
            s_period=None if s_period is None else float(s_period),
        )
        mesh.validate()
        return mesh

    # ------------------------------------------------------------- geometry
    @property
    def periodic(self) -> bool:
        """Whether the s direction is periodic (closed round the bone)."""
        return self.s_period is not None

    @property
    def shape(self) -> tuple[int, int]:
        """(S, T): number of s-lines and t-lines of the global grid."""
        return len(self.s_lines), len(self.t_lines)

    def s_value(self, idx: np.ndarray | int) -> np.ndarray:
        """s knot values of (possibly unwrapped) s-line indices."""
        idx = np.asarray(idx)
        if self.s_period is None:
            return self.s_lines[idx]
        n = len(self.s_lines)
        return self.s_lines[idx % n] + np.floor_divide(idx, n) * self.s_period

    def t_value(self, idx: np.ndarray) -> np.ndarray:
        """t knot values of t-line indices."""
        return self.t_lines[np.asarray(idx)]

    @property
    def s_range(self) -> tuple[float, float]:
        """Parameter range of s: one period, or the clamped ends."""
        if self.periodic:
            return float(self.s_lines[0]), float(self.s_lines[0] + self.s_period)
        return float(self.s_lines[0]), float(self.s_lines[-1])

    @property
    def t_range(self) -> tuple[float, float]:
        """(first, last) t knot line."""
        return float(self.t_lines[0]), float(self.t_lines[-1])

    # ------------------------------------------------------------- topology
    @cached_property
    def on_s(self) -> np.ndarray:
        """(S, T) bool: grid point touched by an edge running in s."""
        return _touch(self.s_edges, self.periodic).T

    @cached_property
    def on_t(self) -> np.ndarray:
        """(S, T) bool: grid point touched by an edge running in t."""
        return _touch(self.t_edges, False)

    @cached_property
    def vertices(self) -> np.ndarray:
        """(S, T) bool: grid points that are T-mesh vertices."""
        return self.on_s & self.on_t

    def _phantom_mask(self) -> np.ndarray:
        """(S, T) bool: grid points on phantom lines (no control points there)."""
        s_n, t_n = self.shape
        mask = np.zeros((s_n, t_n), dtype=bool)
        mask[:, :PHANTOM] = mask[:, t_n - PHANTOM :] = True
        if not self.periodic:
            mask[:PHANTOM, :] = mask[s_n - PHANTOM :, :] = True
        return mask

    @cached_property
    def anchors(self) -> np.ndarray:
        """(n, 2) int: [s-line, t-line] of each control point, ordered by t, then s."""
        jj, ii = np.nonzero((self.vertices & ~self._phantom_mask()).T)
        return np.stack([ii, jj], axis=1)

    @cached_property
    def anchor_knots(self) -> tuple[np.ndarray, np.ndarray]:
        """Local knot indices of every anchor: ((n, 5) s-lines unwrapped, (n, 5) t-lines)."""
        return self.knot_indices(self.anchors)

    def knot_indices(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ray-cast local knot indices of vertices.

        points : (n, 2) int [s-line, t-line] of vertices.
        Returns ((n, 5) int unwrapped s-line indices, (n, 5) int t-line indices).
        """
        points = np.asarray(points, dtype=np.int64).reshape(-1, 2)
        s_idx = ray_cast(self.on_t.T, points[:, 1], points[:, 0], self.periodic)
        t_idx = ray_cast(self.on_s, points[:, 0], points[:, 1], False)
        return s_idx, t_idx

    def edge_flags(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per grid point, (S, T) bool each: edge to the -s, +s, -t and +t side."""
        left, right = _neighbour_flags(self.s_edges, self.periodic)
        down, up = _neighbour_flags(self.t_edges, False)
        return left.T, right.T, down, up

    def point_label(self, i: int, j: int) -> str:
        """Human-readable grid point: indices and knot values."""
        return f"(s={self.s_value(i):.6g}, t={self.t_lines[j]:.6g}; lines {i}, {j})"

    # ----------------------------------------------------------- validation
    def validate(self) -> None:
        """Raise ValueError naming the first rule the mesh breaks."""
        s_n, t_n = self.shape
        _check_lines(self.t_lines, "t_lines", periodic_span=None)
        _check_lines(self.s_lines, "s_lines", periodic_span=self.s_period)
        n_s_seg = s_n if self.periodic else s_n - 1
        if self.s_edges.shape != (t_n, n_s_seg) or self.s_edges.dtype != bool:
            raise ValueError(f"s_edges: expected bool ({t_n}, {n_s_seg}), "
                             f"got {self.s_edges.dtype} {self.s_edges.shape}")
        if self.t_edges.shape != (s_n, t_n - 1) or self.t_edges.dtype != bool:
            raise ValueError(f"t_edges: expected bool ({s_n}, {t_n - 1}), "
                             f"got {self.t_edges.dtype} {self.t_edges.shape}")
        _check_strips(self.s_edges, self.t_edges, "t")
        if not self.periodic:
            _check_strips(self.t_edges, self.s_edges, "s")
        left, right, down, up = self.edge_flags()
        horizontal = left | right
        vertical = down | up
        dangling = ((left ^ right) & ~vertical) | ((down ^ up) & ~horizontal)
        if dangling.any():
            i, j = np.argwhere(dangling)[0]
            raise ValueError(f"invalid T-mesh: an edge ends in the open at {self.point_label(i, j)}")
        corner = (left ^ right) & (down ^ up)
        boundary = np.zeros_like(corner)
        boundary[:, [0, t_n - 1]] = True
        if not self.periodic:
            boundary[[0, s_n - 1], :] = True
        corner &= ~boundary
        if corner.any():
            i, j = np.argwhere(corner)[0]
            raise ValueError(
                f"invalid T-mesh: L-shaped corner inside the domain at {self.point_label(i, j)} "
                "(faces must be rectangles)"
            )
        if len(self.anchors) == 0:
            raise ValueError("invalid T-mesh: no control points")
        s_idx, _ = self.anchor_knots
        if self.s_period is not None:
            span = self.s_value(s_idx[:, 4]) - self.s_value(s_idx[:, 0])
            if np.any(span > self.s_period * (1 + 1e-12)):
                raise ValueError("invalid T-mesh: a blending function spans more than the s period")

    # ------------------------------------------------------ local operations
    def with_line(self, axis: str, value: float, tol: float) -> tuple[TMesh, int, bool]:
        """The same mesh on a grid with one more knot line (no edges added).

        axis : "s" (a line of constant s) or "t". value : its knot value.
        tol : knot values closer than this are the same line.
        Returns (mesh, index of the line, whether it was new). The edges the
        new line cuts are split, so the T-mesh itself is unchanged.
        """
        if axis == "s":
            lines, lo, hi = self.s_lines, *self.s_range
            if self.s_period is not None:
                value = lo + (value - lo) % self.s_period
        else:
            lines, lo, hi = self.t_lines, *self.t_range
        if not lo - tol <= value <= hi + tol:
            raise ValueError(f"{axis} = {value!r} lies outside the parameter range [{lo}, {hi}]")
        near = np.flatnonzero(np.abs(lines - value) <= tol)
        if self.periodic and axis == "s" and near.size == 0 and hi - value <= tol:
            near = np.array([0])
        if near.size:
            k = int(near[0])
            if axis == "t" or not self.periodic:
                # the real boundary line, not a phantom one
                k = min(max(k, END_LINES - 1), len(lines) - END_LINES)
            return self, k, False
        k = int(np.searchsorted(lines, value))  # >= 1: value lies above the first line
        new_lines = np.concatenate([lines[:k], [value], lines[k:]])
        # the new line splits the edges it crosses and carries none itself
        if axis == "s":
            s_edges = np.hstack([self.s_edges[:, :k], self.s_edges[:, k - 1 : k], self.s_edges[:, k:]])
            t_edges = np.vstack([self.t_edges[:k], np.zeros_like(self.t_edges[:1]), self.t_edges[k:]])
            mesh = TMesh(new_lines, self.t_lines, s_edges, t_edges, self.s_period)
        else:
            t_edges = np.hstack([self.t_edges[:, :k], self.t_edges[:, k - 1 : k], self.t_edges[:, k:]])
            s_edges = np.vstack([self.s_edges[:k], np.zeros_like(self.s_edges[:1]), self.s_edges[k:]])
            mesh = TMesh(self.s_lines, new_lines, s_edges, t_edges, self.s_period)
        return mesh, k, True

    def with_edges(self, s_edges: np.ndarray, t_edges: np.ndarray) -> TMesh:
        """The mesh with these edge arrays (same grid), validated."""
        mesh = TMesh(self.s_lines, self.t_lines, s_edges, t_edges, self.s_period)
        mesh.validate()
        return mesh


def _clamped_lines(knots: np.ndarray, name: str) -> np.ndarray:
    """Distinct clamped knots -> grid line values with the end lines repeated."""
    if knots.ndim != 1 or knots.size < 2:
        raise ValueError(f"{name}: expected at least 2 distinct knots, got shape {knots.shape}")
    pad = END_LINES - 1
    return np.concatenate([np.full(pad, knots[0]), knots, np.full(pad, knots[-1])])


def _check_lines(lines: np.ndarray, name: str, periodic_span: float | None) -> None:
    if lines.ndim != 1 or not np.all(np.isfinite(lines)):
        raise ValueError(f"{name}: expected a 1-D array of finite knot values, got shape {lines.shape}")
    if periodic_span is not None:
        if not periodic_span > 0:
            raise ValueError(f"s_period: expected a positive period, got {periodic_span}")
        if lines.size < 4 or np.any(np.diff(lines) <= 0) or lines[-1] - lines[0] >= periodic_span:
            raise ValueError(
                f"{name}: a periodic direction needs at least 4 strictly increasing knots within one "
                f"period ({periodic_span}); got {lines.size} knots spanning {np.ptp(lines) if lines.size else 0}"
            )
        return
    e = END_LINES
    if lines.size < 2 * e:
        raise ValueError(f"{name}: expected at least {2 * e} lines, got {lines.size}")
    if np.any(lines[:e] != lines[0]) or np.any(lines[-e:] != lines[-1]):
        raise ValueError(f"{name}: the first and last {e} lines of a clamped direction must share the end knot")
    if np.any(np.diff(lines[e - 1 : lines.size - e + 1]) <= 0):
        raise ValueError(f"{name}: knot values must increase strictly between the clamped ends")


def _check_strips(along: np.ndarray, across: np.ndarray, axis: str) -> None:
    """The end strips of an open direction must be complete.

    along : edges lying on the lines of that direction (rows = its lines).
    across : edges crossing those lines (columns = its segments).
    """
    e = END_LINES
    if not (along[:e].all() and along[-e:].all()):
        raise ValueError(f"invalid T-mesh: the four boundary {axis}-lines at each clamped end must be complete")
    head, tail = across[:, : e - 1], across[:, -(e - 1) :]
    if np.any(head != across[:, e - 1 : e]) or np.any(tail != across[:, -e : -e + 1]):
        raise ValueError(
            f"invalid T-mesh: every edge reaching a clamped {axis} boundary must continue through its "
            "zero-width end strip (and no others may)"
        )
