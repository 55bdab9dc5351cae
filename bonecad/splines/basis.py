"""B-spline and Bernstein basis functions: the one span search and the one Cox-de Boor kernel.

Everything is vectorised over many parameters at once. ``find_span`` serves
global knot vectors (one increasing array, A2.1) and local ones (one knot
vector per row, as the T-spline's 5-knot vectors); ``basis_functions`` is the
triangle of A2.2 with the derivatives of A2.3; ``design_matrix`` wraps scipy's
sparse collocation matrix (the fastest tool when the knots are shared by all
points) for clamped and periodic curves.

References: L. Piegl, W. Tiller, *The NURBS Book*, 2nd ed. (1997), A2.1 (span),
A2.2 (basis functions), A2.3 (their derivatives), eq. 1.8 (Bernstein).
"""
from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.interpolate import BSpline

from bonecad.splines.knots import unclamped_periodic


def find_span(knots: np.ndarray, t: np.ndarray, degree: int | None = None) -> np.ndarray:
    """Index i of the knot interval knots[i] <= t < knots[i + 1] (NURBS Book A2.1).

    knots : (m,) non-decreasing, or (n, m) with one knot vector per row (then t is (n,)).
    degree : None returns the raw index (-1 before the first knot, m - 1 at or after
        the last); else the index is clamped to the spans of a degree-``degree``
        spline, [degree, m - degree - 2], so that the end of the domain belongs to
        the last span.
    """
    t = np.asarray(t, dtype=np.float64)
    if knots.ndim == 2:
        span = np.sum(knots <= t[:, None], axis=1) - 1
    else:
        span = np.searchsorted(knots, t, side="right") - 1
    if degree is None:
        return span
    return np.clip(span, degree, knots.shape[-1] - degree - 2)


def _divide(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a / b where b != 0, else 0 (the 0/0 := 0 convention of the recurrence)."""
    return np.divide(a, b, out=np.zeros(np.broadcast(a, b).shape), where=b != 0)


def _triangle(knots: np.ndarray, degree: int, t: np.ndarray, span: np.ndarray) -> np.ndarray:
    """(p+1, p+1, N) table of A2.2/A2.3: ndu[r, j] (r <= j) is basis function span - j + r of
    degree j at t; ndu[j, r] (r < j) the knot difference it was divided by."""
    p = degree
    count = len(t)
    ndu = np.zeros((p + 1, p + 1, count))
    ndu[0, 0] = 1.0
    left = np.zeros((p + 1, count))
    right = np.zeros((p + 1, count))
    for j in range(1, p + 1):
        left[j] = t - knots[span + 1 - j]
        right[j] = knots[span + j] - t
        saved = np.zeros(count)
        for r in range(j):
            ndu[j, r] = right[r + 1] + left[j - r]
            temp = _divide(ndu[r, j - 1], ndu[j, r])
            ndu[r, j] = saved + right[r + 1] * temp
            saved = left[j - r] * temp
        ndu[j, j] = saved
    return ndu


def basis_functions(knots: np.ndarray, degree: int, t: np.ndarray, span: np.ndarray, order: int = 0) -> np.ndarray:
    """The p + 1 non-zero basis functions at ``t`` and their derivatives up to ``order``.

    knots : (m,) global knot vector; t : (N,); span : (N,) from :func:`find_span`.
    Returns (order + 1, N, p + 1): [k, i, r] is the k-th derivative of basis function
    span[i] - p + r at t[i] (NURBS Book A2.2, A2.3). The first derivative alone comes
    straight from the degree p - 1 functions (eq. 2.9), which is cheaper than A2.3.
    """
    p = degree
    t = np.asarray(t, dtype=np.float64)
    count = len(t)
    ndu = _triangle(knots, p, t, span)
    ders = np.zeros((order + 1, count, p + 1))
    ders[0] = ndu[:, p].T
    if order == 0 or p == 0:
        return ders
    if order == 1:
        lower = ndu[:p, p - 1]  # (p, N): the degree p - 1 functions
        for r in range(p + 1):
            i = span - p + r
            if r >= 1:
                ders[1, :, r] += _divide(p * lower[r - 1], knots[i + p] - knots[i])
            if r <= p - 1:
                ders[1, :, r] -= _divide(p * lower[r], knots[i + p + 1] - knots[i + 1])
        return ders
    for r in range(p + 1):
        a = np.zeros((2, p + 1, count))
        a[0, 0] = 1.0
        s1, s2 = 0, 1
        for k in range(1, order + 1):
            d = np.zeros(count)
            rk, pk = r - k, p - k
            if r >= k:
                a[s2, 0] = _divide(a[s1, 0], ndu[pk + 1, rk])
                d += a[s2, 0] * ndu[rk, pk]
            j1 = 1 if rk >= -1 else -rk
            j2 = k - 1 if r - 1 <= pk else p - r
            for j in range(j1, j2 + 1):
                a[s2, j] = _divide(a[s1, j] - a[s1, j - 1], ndu[pk + 1, rk + j])
                d += a[s2, j] * ndu[rk + j, pk]
            if r <= pk:
                a[s2, k] = _divide(-a[s1, k - 1], ndu[pk + 1, r])
                d += a[s2, k] * ndu[r, pk]
            ders[k, :, r] = d
            s1, s2 = s2, s1
    factor = p
    for k in range(1, order + 1):
        ders[k] *= factor
        factor *= p - k
    return ders


def design_matrix(u: np.ndarray, knots: np.ndarray, degree: int, periodic: bool, count: int) -> sparse.csr_matrix:
    """(len(u), count) sparse collocation matrix N_j(u_i) of a curve's basis (scipy's).

    knots : the clamped knot sequence, or for a periodic basis the count + 1 uniform
    knots of one period (:mod:`bonecad.splines.knots`); periodic parameters wrap into [0, 1).
    """
    if not periodic:
        return BSpline.design_matrix(u, knots, degree).tocsr()
    full = BSpline.design_matrix(np.mod(u, 1.0), unclamped_periodic(count, degree), degree).tocoo()
    return sparse.csr_matrix((full.data, (full.row, full.col % count)), shape=(len(u), count))


def bernstein3(u: np.ndarray, order: int = 0) -> np.ndarray:
    """Cubic Bernstein polynomials on [0, 1] and their derivatives in u.

    u : (n,) float. Returns (order + 1, n, 4) float.
    """
    v = 1.0 - u
    uu, vv, uv = u * u, v * v, u * v
    out = np.empty((order + 1, len(u), 4))
    out[0, :, 0] = vv * v
    out[0, :, 1] = 3.0 * uv * v
    out[0, :, 2] = 3.0 * uv * u
    out[0, :, 3] = uu * u
    if order >= 1:
        out[1, :, 0] = -3.0 * vv
        out[1, :, 1] = 3.0 * (vv - 2.0 * uv)
        out[1, :, 2] = 3.0 * (2.0 * uv - uu)
        out[1, :, 3] = 3.0 * uu
    if order >= 2:
        out[2, :, 0] = 6.0 * v
        out[2, :, 1] = 6.0 * (u - 2.0 * v)
        out[2, :, 2] = 6.0 * (v - 2.0 * u)
        out[2, :, 3] = 6.0 * u
    return out
