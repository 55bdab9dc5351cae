"""The spline kernel's basis functions and span search (bonecad.splines.basis, .knots)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import BSpline

from bonecad.splines.basis import basis_functions, bernstein3, design_matrix, find_span
from bonecad.splines.knots import full_sequence, multiplicities, periodic_knots, unclamped_periodic, wrapped_poles

KNOTS = np.array([0.0, 0.0, 0.0, 0.0, 0.1, 0.35, 0.35, 0.6, 0.9, 1.0, 1.0, 1.0, 1.0])  # a double knot inside


def _values(knots, degree, t, order=0):
    """(order + 1, N, n) basis functions and derivatives by the kernel, scattered to all n functions."""
    span = find_span(knots, t, degree)
    ders = basis_functions(knots, degree, t, span, order)
    n = len(knots) - degree - 1
    out = np.zeros((order + 1, len(t), n))
    cols = span[:, None] - degree + np.arange(degree + 1)
    for k in range(order + 1):
        np.put_along_axis(out[k], cols, ders[k], axis=1)
    return out


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_basis_matches_scipy_and_sums_to_one(degree):
    knots = np.concatenate([[0.0] * degree, KNOTS[3:-3], [1.0] * degree]) if degree != 3 else KNOTS
    t = np.linspace(0.0, 1.0, 301)
    ours = _values(knots, degree, t, order=min(degree, 2))
    n = len(knots) - degree - 1
    for k in range(ours.shape[0]):
        ref = np.stack([BSpline(knots, np.eye(n)[j], degree)(t, nu=k) for j in range(n)], axis=1)
        inside = ~np.isin(t, knots) if k else np.ones(len(t), bool)  # derivatives jump at knots
        np.testing.assert_allclose(ours[k][inside], ref[inside], atol=1e-10)
    np.testing.assert_allclose(ours[0].sum(axis=1), 1.0, atol=1e-14)
    if degree >= 1:
        np.testing.assert_allclose(ours[1].sum(axis=1), 0.0, atol=1e-10)


def test_derivatives_by_finite_differences():
    t = np.linspace(0.02, 0.98, 97)
    t = t[np.min(np.abs(t[:, None] - KNOTS[None]), axis=1) > 1e-3]
    h = 1e-6
    d = _values(KNOTS, 3, t, order=3)
    plus, minus = _values(KNOTS, 3, t + h), _values(KNOTS, 3, t - h)
    np.testing.assert_allclose(d[1], (plus[0] - minus[0]) / (2 * h), atol=1e-6)
    d1p, d1m = _values(KNOTS, 3, t + h, order=1)[1], _values(KNOTS, 3, t - h, order=1)[1]
    np.testing.assert_allclose(d[2], (d1p - d1m) / (2 * h), atol=1e-4)
    d2p, d2m = _values(KNOTS, 3, t + h, order=2)[2], _values(KNOTS, 3, t - h, order=2)[2]
    np.testing.assert_allclose(d[3], (d2p - d2m) / (2 * h), atol=1e-2 * np.abs(d[3]).max())


def test_first_derivative_shortcut_equals_a23():
    t = np.random.default_rng(0).random(200)
    span = find_span(KNOTS, t, 3)
    np.testing.assert_allclose(basis_functions(KNOTS, 3, t, span, 1)[1], basis_functions(KNOTS, 3, t, span, 2)[1],
                               rtol=1e-12, atol=1e-12)


def test_span_search_edge_cases():
    # interior knots go to the span they open; the domain's ends to the first and last span
    t = np.array([-0.5, 0.0, 0.05, 0.1, 0.35, 0.99, 1.0, 1.5])
    np.testing.assert_array_equal(find_span(KNOTS, t, 3), [3, 3, 3, 4, 6, 8, 8, 8])
    # raw search: -1 before the first knot, last index at or after the last
    np.testing.assert_array_equal(find_span(KNOTS, t), [-1, 3, 3, 4, 6, 8, 12, 12])
    # a double knot: its value belongs to the span after it, the empty span between is never returned
    assert find_span(KNOTS, np.array([0.35]), 3)[0] == 6
    # one knot vector per row
    rows = np.array([[0.0, 1.0, 2.0, 3.0, 4.0], [0.0, 0.0, 1.0, 1.0, 2.0]])
    np.testing.assert_array_equal(find_span(rows, np.array([2.5, 1.0])), [2, 3])


def test_periodic_design_matrix_wraps_the_basis():
    count, degree = 7, 3
    u = np.linspace(0.0, 1.0, 50, endpoint=False)
    a = design_matrix(u, periodic_knots(count), degree, True, count).toarray()
    np.testing.assert_allclose(a.sum(axis=1), 1.0, atol=1e-14)
    poles = np.random.default_rng(1).random((count, 3))
    ref = BSpline(unclamped_periodic(count, degree), wrapped_poles(poles, degree), degree)(u)
    np.testing.assert_allclose(a @ poles, ref, atol=1e-14)
    np.testing.assert_allclose(design_matrix(u + 1.0, periodic_knots(count), degree, True, count).toarray(), a,
                               atol=1e-12)


def test_knots_and_multiplicities_round_trip():
    values, mults = multiplicities(KNOTS + np.where(KNOTS == 0.35, 1e-16, 0.0))
    np.testing.assert_array_equal(mults, [4, 1, 2, 1, 1, 4])
    np.testing.assert_allclose(full_sequence(values, mults), KNOTS)


def test_bernstein_partition_and_derivatives():
    u = np.linspace(0.0, 1.0, 41)
    b = bernstein3(u, 2)
    np.testing.assert_allclose(b[0].sum(axis=1), 1.0, atol=1e-14)
    np.testing.assert_allclose(b[1].sum(axis=1), 0.0, atol=1e-12)
    clamped = np.array([0.0] * 4 + [1.0] * 4)  # one cubic Bezier span: the B-spline basis is Bernstein's
    np.testing.assert_allclose(_values(clamped, 3, u, order=2), b.transpose(0, 1, 2), atol=1e-12)
