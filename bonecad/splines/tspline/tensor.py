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
  kept), e.g. a plate's footprint on a bone.
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
        turns = np.arange(np.floor((s0 - mesh.s_lines[0]) / mesh.s_period) - 1,
                          np.ceil((s1 - mesh.s_lines[0]) / mesh.s_period) + 1)
        s_lines = (mesh.s_lines[None, :] + mesh.s_period * turns[:, None]).ravel()
    else:
        lo_s, hi_s = mesh.s_range
        if not (lo_s <= s0 < s1 <= hi_s):
            raise ValueError(f"s range [{s0}, {s1}] is not an interval inside [{lo_s}, {hi_s}]")
        s_lines = mesh.s_lines
    knots_u, knots_v = _clamped_knots(s_lines, s0, s1), _clamped_knots(mesh.t_lines, t0, t1)
    gu, gv = _greville(knots_u), _greville(knots_v)
    uu, vv = np.meshgrid(gu, gv, indexing="ij")
    values = ts.evaluate(_wrapped(mesh, uu.ravel()), vv.ravel()).points.reshape(len(gu), len(gv), 3)
    poles = _solve_tensor(_collocation(gu, knots_u, None), _collocation(gv, knots_v, None), values)
    patch = BSplineSurface(poles, knots_u, knots_v, 3, 3, region=region)
    s, t = _samples(knots_u), _samples(knots_v)
    ss, tt = (a.ravel() for a in np.meshgrid(s, t))
    _check(ts.evaluate(_wrapped(mesh, ss), tt).points, patch.evaluate(ss, tt).points, "the region patch")
    return patch


def _wrapped(mesh, s: np.ndarray) -> np.ndarray:
    """s brought into the T-spline's period (periodic s), else unchanged."""
    if not mesh.periodic:
        return s
    lo = mesh.s_lines[0]
    return lo + np.mod(s - lo, mesh.s_period)
