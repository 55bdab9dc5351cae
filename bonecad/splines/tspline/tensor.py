"""A polynomial T-spline as tensor-product B-splines, exactly: whole (global knot lines) or a rectangle.

Every blending function of a T-spline is a cubic B-spline on local knots taken
from the T-mesh's knot lines, so it lies in the tensor-product spline space of
*all* the lines (single knots: knot insertion never leaves it). The surface is
therefore exactly a tensor-product B-spline on the global lines, and its
restriction to a rectangle [s0, s1] x [t0, t1] exactly a clamped one whose
interior knots are the lines strictly inside. Both are found by interpolating
the T-spline at the Greville points of that space (Schoenberg-Whitney holds
there, so the square system is regular): exact up to rounding, which is
checked (``EXACT_MM``).

- :func:`tensor_product_form`: the whole T-spline on its global lines (a
  tensor-product T-spline: periodic in s when the T-spline is);
- :func:`region_patch`: the rectangle as one clamped, untrimmed
  :class:`~bonecad.splines.surface.BSplineSurface` (u = s, v = t, parameters
  kept), e.g. a plate's footprint on a bone. Its interior knots are only the
  element boundaries inside the rectangle (where the surface may break), so a
  rectangle that a T-junction's line does not cross has no knot there;
- :func:`panel_plan`: rectangles covering the T-spline with the fewest poles
  (a lean B-rep: one exact B-spline face per rectangle).
"""
from __future__ import annotations

import numpy as np
from scipy.interpolate import BSpline

from bonecad.errors import FitError
from bonecad.splines.surface import BSplineSurface
from bonecad.splines.tspline.tspline import TSpline

#: Largest distance (mm) between a T-spline and its tensor-product form at the check samples.
EXACT_MM = 1e-7
#: Check samples per knot interval and direction.
_CHECKS = 1


def _polynomial(ts: TSpline) -> None:
    if not ts.polynomial:
        raise FitError("the tensor-product form is implemented for polynomial T-splines (all weights 1)")


def _check(expected: np.ndarray, found: np.ndarray, what: str) -> float:
    """Largest distance (mm) between the T-spline's points and another form's; FitError beyond EXACT_MM."""
    gap = float(np.linalg.norm(expected - found, axis=1).max())
    if gap > EXACT_MM:
        raise FitError(f"{what} misses the T-spline by {gap:.3g} mm (more than rounding: {EXACT_MM} mm)")
    return gap


def _samples(lines: np.ndarray) -> np.ndarray:
    """Points inside every interval between consecutive distinct ``lines`` (and the ends)."""
    lines = np.unique(lines)
    inner = [lines[:-1] + f * np.diff(lines) for f in (np.arange(1, _CHECKS + 1) / (_CHECKS + 1))]
    return np.concatenate([lines, *inner])


def _collocation(x: np.ndarray, lines: np.ndarray, period: float | None) -> np.ndarray:
    """(len(x), m) values of the cubic B-splines on knot ``lines`` (the T-mesh convention: periodic with
    ``period``, m = len(lines), function i on lines i-2..i+2; else the lines are a clamped knot vector
    with four equal lines at each end, m = len(lines) - 4) at ``x``."""
    if period is None:  # (a mean of equal knots can round past the end)
        return BSpline.design_matrix(np.clip(x, lines[3], lines[-4]), lines, 3).toarray()
    n = len(lines)
    k = np.arange(-3, n + 4)
    unrolled = lines[k % n] + np.floor_divide(k, n) * period
    lo = lines[0]
    x = lo + np.mod(x - lo, period)
    values = BSpline.design_matrix(x, unrolled, 3).toarray()  # columns: function i - 1 (mod n)
    folded = np.zeros((len(x), n))
    np.add.at(folded.T, (np.arange(values.shape[1]) - 1) % n, values.T)
    return folded


def tensor_product_form(ts: TSpline) -> TSpline:
    """The same surface as a tensor-product T-spline on all of ``ts``'s knot lines (exact, checked)."""
    _polynomial(ts)
    mesh = ts.mesh
    period = mesh.s_period if mesh.periodic else None
    s_lines, t_lines = mesh.s_lines, mesh.t_lines
    if period is None:
        greville_s = _greville(s_lines)
    else:
        n = len(s_lines)
        k = np.arange(-1, n + 1)
        unrolled = s_lines[k % n] + np.floor_divide(k, n) * period
        greville_s = (unrolled[:-2] + unrolled[1:-1] + unrolled[2:]) / 3.0
    greville_t = _greville(t_lines)
    a_s, a_t = _collocation(greville_s, s_lines, period), _collocation(greville_t, t_lines, None)
    ss, tt = np.meshgrid(greville_s, greville_t, indexing="ij")
    values = ts.evaluate(_wrapped(mesh, ss.ravel()), tt.ravel()).points.reshape(len(greville_s), len(greville_t), 3)
    poles = _solve_tensor(a_s, a_t, values)
    # check between the Greville points
    s_check = _samples(np.append(s_lines, mesh.s_range[1]))[:-1] if period else _samples(s_lines)
    t_check = _samples(t_lines)
    ss, tt = np.meshgrid(s_check, t_check, indexing="ij")
    found = np.einsum("ai,ijk,bj->abk", _collocation(s_check, s_lines, period), poles,
                      _collocation(t_check, t_lines, None), optimize=True)
    _check(ts.evaluate(_wrapped(mesh, ss.ravel()), tt.ravel()).points, found.reshape(-1, 3), "the tensor-product form")
    if period is None:
        return TSpline.from_grid(np.unique(s_lines), np.unique(t_lines), poles)
    return TSpline.from_grid(s_lines, np.unique(t_lines), poles, s_period=period)


def _solve_tensor(a_u: np.ndarray, a_v: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Poles P with a_u @ P @ a_v.T = values (per coordinate), one direction after the other."""
    nu, nv = a_u.shape[1], a_v.shape[1]
    poles = np.linalg.solve(a_u, values.reshape(len(a_u), -1)).reshape(nu, -1, 3)
    return np.linalg.solve(a_v, poles.transpose(1, 0, 2).reshape(len(a_v), -1)).reshape(nv, nu, 3).transpose(1, 0, 2)


def _clamped_knots(lines: np.ndarray, lo: float, hi: float) -> np.ndarray:
    inside = np.unique(lines[(lines > lo) & (lines < hi)])
    return np.concatenate([np.full(4, lo), inside, np.full(4, hi)])


def _greville(knots: np.ndarray) -> np.ndarray:
    count = len(knots) - 4
    return np.array([knots[i + 1:i + 4].mean() for i in range(count)])


def region_patch(ts: TSpline, s_range: tuple[float, float], t_range: tuple[float, float], *,
                 region: str = "patch") -> BSplineSurface:
    """The T-spline over the rectangle s_range x t_range as one clamped bicubic B-spline surface (exact,
    checked to ``EXACT_MM``).

    s_range may run past the end of a periodic s (s0 < s1, s1 - s0 < the period); its
    parameters are kept (u = s unwrapped, v = t). t_range must lie inside the T-spline.
    """
    _polynomial(ts)
    mesh = ts.mesh
    (s0, s1), (t0, t1) = (map(float, s_range)), (map(float, t_range))
    lo_t, hi_t = mesh.t_range
    if not (lo_t <= t0 < t1 <= hi_t):
        raise ValueError(f"t range [{t0}, {t1}] is not an interval inside [{lo_t}, {hi_t}]")
    if mesh.s_period is not None:
        if not (s0 < s1 and s1 - s0 < mesh.s_period):
            raise ValueError(f"s range [{s0}, {s1}] must be increasing and shorter than the period {mesh.s_period}")
    else:
        lo_s, hi_s = mesh.s_range
        if not (lo_s <= s0 < s1 <= hi_s):
            raise ValueError(f"s range [{s0}, {s1}] is not an interval inside [{lo_s}, {hi_s}]")
    s_breaks, t_breaks = _element_breaks(ts, (s0, s1), (t0, t1))
    knots_u, knots_v = _clamped_knots(s_breaks, s0, s1), _clamped_knots(t_breaks, t0, t1)
    gu, gv = _greville(knots_u), _greville(knots_v)
    uu, vv = np.meshgrid(gu, gv, indexing="ij")
    values = ts.evaluate(_wrapped(mesh, uu.ravel()), vv.ravel()).points.reshape(len(gu), len(gv), 3)
    poles = _solve_tensor(_collocation(gu, knots_u, None), _collocation(gv, knots_v, None), values)
    patch = BSplineSurface(poles, knots_u, knots_v, 3, 3, region=region)
    s, t = _samples(knots_u), _samples(knots_v)
    ss, tt = (a.ravel() for a in np.meshgrid(s, t))
    _check(ts.evaluate(_wrapped(mesh, ss), tt).points, patch.evaluate(ss, tt).points, "the region patch")
    return patch


def _element_breaks(ts: TSpline, s_range: tuple[float, float], t_range: tuple[float, float]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The s and t values of the Bezier element boundaries of ``ts`` that meet the open rectangle
    s_range x t_range (s unwrapped like s_range): the only places inside it where the surface
    may break, so the knots its exact B-spline form needs there."""
    ext = ts.extraction
    (s0, s1), (t0, t1) = s_range, t_range
    period = ts.mesh.s_period
    shifts = np.arange(np.floor((s0 - ext.s_bounds.max()) / period), np.ceil((s1 - ext.s_bounds.min()) / period) + 1
                       ) * period if period is not None else np.zeros(1)
    s_bounds = (ext.s_bounds[None, :, :] + shifts[:, None, None]).reshape(-1, 2)
    t_bounds = np.tile(ext.t_bounds, (len(shifts), 1))
    meets = (s_bounds[:, 0] < s1) & (s_bounds[:, 1] > s0) & (t_bounds[:, 0] < t1) & (t_bounds[:, 1] > t0)
    return s_bounds[meets].ravel(), t_bounds[meets].ravel()


def panel_plan(ts: TSpline, *, t_cuts: tuple[float, ...] = (), face_cost: float, t_step: int
               ) -> tuple[tuple[float, float, float, float], ...]:
    """Rectangles (s0, s1, t0, t1) that tile the T-spline's domain, chosen for the fewest poles of their
    exact B-spline forms (:func:`region_patch`): a guillotine plan of strips across t, each cut
    across s, found by dynamic programming.

    The cost of a rectangle is its poles, plus the poles of two of its four sides (a side's boundary
    curve, shared with the neighbour), plus ``face_cost`` (a face's own entities in a B-rep). Strips
    start and end on every ``t_step``-th t-line and on the lines of ``t_cuts`` (which they never
    cross); panels start and end on s-lines and never close round s: every strip is cut at the
    first s-line. For a tube (periodic s). Deterministic.
    """
    ext = ts.extraction
    mesh = ts.mesh
    if not mesh.periodic:
        raise ValueError("a panel plan is made for a tube (periodic s)")
    cells = ext.cell_element
    n_s, n_t = cells.shape
    columns = np.nonzero((cells >= 0).all(axis=0))[0]  # t cells of nonzero height
    first, end = int(columns[0]), int(columns[-1]) + 1
    forced = [int(np.argmin(np.abs(mesh.t_lines[first:end + 1] - t))) + first for t in t_cuts]
    candidates = sorted({*range(first, end, t_step), end, *forced})
    # s_break[k, j]: s-line k separates different elements in t cell j; t_break[k, l]: t-line l does in s cell k
    s_break = cells != np.roll(cells, 1, axis=0)
    t_break = np.zeros((n_s, n_t + 1), dtype=bool)
    t_break[:, 1:-1] = cells[:, 1:] != cells[:, :-1]
    def strip(c: int, d: int) -> tuple[float, list[int]]:
        """The cheapest cut of t cells c..d-1 across s: (cost, s-line indices of the cuts)."""
        inside_s = np.concatenate([[0], np.cumsum(s_break[:, c:d].any(axis=1))])
        # t-lines c+1..d-1 that break in some s cell of a..b-1: the first such cell from a, per line
        rows = t_break[:, c + 1:d]
        nxt = np.where(rows, np.arange(n_s)[:, None], n_s)
        nxt = np.minimum.accumulate(nxt[::-1], axis=0)[::-1]
        counts = np.zeros((n_s, n_s + 2), dtype=np.int64)
        np.add.at(counts, (np.repeat(np.arange(n_s), rows.shape[1]), nxt.ravel() + 1), 1)
        inside_t = np.cumsum(counts, axis=1)[:, :n_s + 1]  # [a, b]: t-lines breaking in cells a..b-1
        a, b = np.triu_indices(n_s + 1, 1)  # a panel from s-line a to s-line b (line n_s: line 0 a turn on)
        nu = inside_s[b] - inside_s[a + 1] + 4
        nv = inside_t[a, b] + 4
        cost = np.full((n_s + 1, n_s + 1), np.inf)
        cost[a, b] = nu * nv + nu + nv + face_cost
        cost[0, n_s] = np.inf  # never round the whole tube
        best = np.full(n_s + 1, np.inf)
        best[0] = 0.0
        back = np.zeros(n_s + 1, dtype=np.int64)
        for k in range(1, n_s + 1):
            totals = best[:k] + cost[:k, k]
            back[k] = int(np.argmin(totals))
            best[k] = totals[back[k]]
        cuts = [n_s]
        while cuts[-1] > 0:
            cuts.append(int(back[cuts[-1]]))
        return float(best[n_s]), cuts[::-1]

    n_c = len(candidates)
    strips = {(i, j): strip(candidates[i], candidates[j]) for i in range(n_c) for j in range(i + 1, n_c)
              if not any(candidates[i] < f < candidates[j] for f in forced)}
    best = np.full(n_c, np.inf)
    best[0] = 0.0
    back = np.zeros(n_c, dtype=np.int64)
    for j in range(1, n_c):
        for i in range(j):
            if (i, j) in strips and best[i] + strips[i, j][0] < best[j]:
                best[j], back[j] = best[i] + strips[i, j][0], i
    t_cuts_idx = [n_c - 1]
    while t_cuts_idx[-1] > 0:
        t_cuts_idx.append(int(back[t_cuts_idx[-1]]))
    t_cuts_idx = t_cuts_idx[::-1]
    s_value = np.append(mesh.s_lines, mesh.s_lines[0] + mesh.s_period)
    panels: list[tuple[float, float, float, float]] = []
    for i, j in zip(t_cuts_idx, t_cuts_idx[1:]):
        t0, t1 = float(mesh.t_lines[candidates[i]]), float(mesh.t_lines[candidates[j]])
        s_cuts = strips[i, j][1]
        panels.extend((float(s_value[a]), float(s_value[b]), t0, t1) for a, b in zip(s_cuts, s_cuts[1:]))
    return tuple(panels)


def _wrapped(mesh, s: np.ndarray) -> np.ndarray:
    """s brought into the T-spline's period (periodic s), else unchanged."""
    if not mesh.periodic:
        return s
    lo = mesh.s_lines[0]
    return lo + np.mod(s - lo, mesh.s_period)
