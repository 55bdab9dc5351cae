"""The one numpy surface type (bonecad.splines.surface): periodic and rational evaluation against
OpenCascade, derivative orders that agree, bounds and reversal."""
from __future__ import annotations

import numpy as np
import pytest

from bonecad.occ import surfaces as occ
from bonecad.splines.knots import periodic_knots
from bonecad.splines.surface import BSplineSurface, SurfaceSet


def periodic_rational(rng) -> BSplineSurface:
    """Periodic in u (7 poles), clamped in v with an inner double knot, random weights."""
    knots_v = np.array([0, 0, 0, 0, 0.4, 0.4, 1, 1, 1, 1.0])
    return BSplineSurface(rng.normal(size=(7, 6, 3)), periodic_knots(7), knots_v, periodic_u=True,
                          weights=rng.uniform(0.5, 2.0, (7, 6)))


def _occ_derivatives(geom, u, v) -> np.ndarray:
    """(N, 6, 3): S, S_u, S_v, S_uu, S_uv, S_vv by Geom_BSplineSurface.D2."""
    from OCP.gp import gp_Pnt, gp_Vec

    out = np.empty((len(u), 6, 3))
    for i, (a, b) in enumerate(zip(u, v)):
        p, vecs = gp_Pnt(), [gp_Vec() for _ in range(5)]
        geom.D2(float(a), float(b), p, *vecs[:2], vecs[2], vecs[4], vecs[3])  # D2U, D2V, D2UV
        out[i] = [[p.X(), p.Y(), p.Z()]] + [[w.X(), w.Y(), w.Z()] for w in vecs]
    return out


def test_periodic_rational_surface_matches_opencascade_to_second_order():
    rng = np.random.default_rng(5)
    surface = periodic_rational(rng)
    geom = occ.to_geom_surface(surface)
    assert geom.IsUPeriodic() and geom.IsURational()
    u, v = rng.uniform(-0.5, 1.5, 60), rng.random(60)  # u outside [0, 1) wraps round
    sample = surface.evaluate(u, v, order=2)
    want = _occ_derivatives(geom, np.mod(u, 1.0), v)
    got = (sample.points, sample.du, sample.dv, sample.duu, sample.duv, sample.dvv)
    for k in range(6):
        np.testing.assert_allclose(got[k], want[:, k], atol=1e-8 * (1 + np.abs(want[:, k]).max()))


def test_orders_agree_and_a_set_evaluates_like_its_surfaces():
    rng = np.random.default_rng(6)
    a, b = periodic_rational(rng), periodic_rational(rng).reversed_v()
    u, v = rng.random(40), rng.random(40)
    zero, one, two = (a.evaluate(u, v, order=k) for k in (0, 1, 2))
    assert np.array_equal(zero.points, one.points)
    np.testing.assert_allclose(two.points, one.points, atol=1e-12)
    np.testing.assert_allclose(two.du, one.du, atol=1e-10)
    with pytest.raises(ValueError, match="du was not evaluated"):
        _ = zero.du
    face = np.tile([0, 1], 20)
    both = SurfaceSet([a, b, None]).evaluate(face, u, v, order=1).points
    np.testing.assert_array_equal(both[face == 0], a.evaluate(u[face == 0], v[face == 0]).points)
    np.testing.assert_array_equal(both[face == 1], b.evaluate(u[face == 1], v[face == 1]).points)
    with pytest.raises(ValueError, match="without a spline surface"):
        SurfaceSet([a, None]).evaluate(np.array([1]), np.array([0.5]), np.array([0.5]))


def test_bounds_default_to_the_knot_domain_and_reversal_keeps_points():
    rng = np.random.default_rng(7)
    surface = periodic_rational(rng)
    assert np.array_equal(surface.bounds, [0.0, 1.0, 0.0, 1.0])
    assert SurfaceSet([surface]).closed.tolist() == [[True, False]]
    trimmed = BSplineSurface(surface.poles, surface.knots_u, surface.knots_v, periodic_u=True,
                             weights=surface.weights, bounds=np.array([np.nan, np.nan, 0.2, 0.7]))
    assert np.array_equal(trimmed.bounds, [0.0, 1.0, 0.2, 0.7])
    assert np.array_equal(trimmed.reversed_v().bounds, [0.0, 1.0, 1.0 - 0.7, 1.0 - 0.2])
    u, v = rng.random(30), rng.random(30)
    np.testing.assert_allclose(surface.reversed_v().evaluate(u, 1.0 - v).points, surface.evaluate(u, v).points,
                               atol=1e-10)
    with pytest.raises(ValueError, match="weights"):
        BSplineSurface(surface.poles, surface.knots_u, surface.knots_v, periodic_u=True, weights=np.ones((7, 5)))
