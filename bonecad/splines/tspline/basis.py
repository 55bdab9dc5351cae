"""Cubic univariate building blocks of T-splines: one B-spline basis function on
its five local knots, its Bernstein coefficients, and Boehm's split of it.

Everything here is vectorised over many functions/points at once and has no
knowledge of T-meshes. Formulas: Piegl & Tiller, The NURBS Book, 2nd ed.,
eqs. 2.5 and 2.9 (Cox-de Boor recurrence and its derivative); Boehm's knot
insertion (ibid. eq. 5.11) restricted to a single basis function.
"""
from __future__ import annotations

import numpy as np

from bonecad.splines.basis import find_span


def _inv(d: np.ndarray) -> np.ndarray:
    """1/d where d > 0, else 0 (the 0/0 := 0 convention of the recurrence)."""
    out = np.zeros_like(d)
    np.divide(1.0, d, out=out, where=d > 0)
    return out


def knot_span(knots: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Index r in 0..3 of the half-open knot interval [k_r, k_r+1) holding x.

    knots : (n, 5) float, non-decreasing rows; x : (n,) float.
    Returns (n,) int; -1 where x lies outside [k_0, k_4).
    """
    r = find_span(knots, x)
    return np.where((r >= 0) & (r <= 3), r, -1)


def bspline5(knots: np.ndarray, x: np.ndarray, span: np.ndarray, order: int = 0) -> np.ndarray:
    """Cubic B-spline basis function N[k0..k4] and its derivatives.

    knots : (n, 5) float, one local knot vector per row.
    x : (n,) float, where to evaluate.
    span : (n,) int in -1..3; the polynomial piece (knot interval) to use. Using
        the piece of an interval's midpoint lets x sit on its ends (one-sided
        values); -1 gives zero (x outside the support).
    order : highest derivative, 0..2.

    Returns (order + 1, n) float: N, dN/dx, d2N/dx2.
    """
    k = knots
    n0 = np.stack([(span == r).astype(np.float64) for r in range(4)])  # (4, n)

    def step(prev: np.ndarray, p: int) -> tuple[np.ndarray, np.ndarray]:
        """Degree-p functions from degree p-1 ones, and their derivatives."""
        vals, ders = [], []
        for r in range(4 - p):
            a = _inv(k[:, r + p] - k[:, r])
            b = _inv(k[:, r + p + 1] - k[:, r + 1])
            vals.append((x - k[:, r]) * a * prev[r] + (k[:, r + p + 1] - x) * b * prev[r + 1])
            ders.append(p * (a * prev[r] - b * prev[r + 1]))
        return np.stack(vals), np.stack(ders)

    n1, _ = step(n0, 1)
    n2, d2 = step(n1, 2)
    n3, d3 = step(n2, 3)
    out = [n3[0]]
    if order >= 1:
        out.append(d3[0])
    if order >= 2:
        a = _inv(k[:, 3] - k[:, 0])
        b = _inv(k[:, 4] - k[:, 1])
        out.append(3.0 * (a * d2[0] - b * d2[1]))
    return np.stack(out)


def bezier_coefficients(knots: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Bernstein coefficients of N[knots] restricted to [a, b] (a cubic piece).

    knots : (n, 5); a, b : (n,) with [a, b] inside one knot interval.
    Returns (n, 4): c with N(a + (b - a) u) = sum_i c_i B_i(u). Exact for a
    cubic: end values and end slopes fix the Bezier polygon.
    """
    span = knot_span(knots, 0.5 * (a + b))
    fa = bspline5(knots, a, span, order=1)
    fb = bspline5(knots, b, span, order=1)
    h = (b - a) / 3.0
    return np.stack([fa[0], fa[0] + h * fa[1], fb[0] - h * fb[1], fb[0]], axis=1)


def split_coefficients(knots: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boehm's split of cubic basis functions, each at a new knot k.

    knots : (n, 5) float; k : (n,) float with x0 < k < x4 per row x.
    N[x0..x4] = c1 N[first five of x + {k}] + c2 N[last five] (ties with
    existing knot values allowed: index order decides). Returns (n,) c1, c2.
    """
    x0, x1, _, x3, x4 = knots.T
    with np.errstate(divide="ignore", invalid="ignore"):
        c1 = np.where(k >= x3, 1.0, (k - x0) / (x3 - x0))
        c2 = np.where(k <= x1, 1.0, (x4 - k) / (x4 - x1))
    return c1, c2
