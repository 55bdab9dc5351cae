"""A T-spline with T-junctions as tensor-product B-splines: exactly, whole and over a rectangle."""
from __future__ import annotations

import numpy as np
import pytest

from bonecad.errors import FitError
from bonecad.splines.tspline import TSpline, check_suitability
from bonecad.splines.tspline.refine import refine_elements
from bonecad.splines.tspline.tensor import panel_plan, region_patch, tensor_product_form


def _t_spline(rng, periodic: bool) -> TSpline:
    """A cylinder-like T-spline, locally refined (T-junctions), its control points then moved at random."""
    s_knots = np.sort(rng.uniform(0.0, 10.0, 9)) if periodic else np.array([0.0, 1.0, 2.5, 3.0, 4.5, 6.0])
    t_knots = np.array([0.0, 1.0, 1.5, 3.0, 4.0, 6.0, 7.0])
    m_s = len(s_knots) if periodic else len(s_knots) + 2
    m_t = len(t_knots) + 2
    grid = rng.normal(size=(m_s, m_t, 3))
    ts = TSpline.from_grid(s_knots, t_knots, grid, s_period=20.0 if periodic else None)
    ts = refine_elements(ts, [1, 5, 12]).tspline
    assert not (ts.mesh.s_edges.all() and ts.mesh.t_edges.all())  # T-junctions
    assert check_suitability(ts.mesh).suitable
    return ts.with_control_points(ts.control_points + rng.normal(scale=0.3, size=ts.control_points.shape))


@pytest.mark.parametrize("periodic", [True, False])
def test_tensor_product_form_is_the_same_surface_on_every_knot_line(rng, periodic):
    ts = _t_spline(rng, periodic)
    tensor = tensor_product_form(ts)
    assert tensor.mesh.s_edges.all() and tensor.mesh.t_edges.all()
    assert np.array_equal(np.unique(tensor.mesh.s_lines), np.unique(ts.mesh.s_lines))
    assert tensor.n_control > ts.n_control
    (s0, s1), (t0, t1) = ts.mesh.s_range, ts.mesh.t_range
    s, t = rng.uniform(s0, s1, 2000), rng.uniform(t0, t1, 2000)
    assert np.abs(tensor.evaluate(s, t).points - ts.evaluate(s, t).points).max() < 1e-9


def test_region_patch_is_exact_across_the_periodic_start(rng):
    ts = _t_spline(rng, True)
    s_start, _ = ts.mesh.s_range
    s_range, t_range = (s_start - 3.3, s_start + 4.1), (0.7, 5.2)  # crosses s = start
    patch = region_patch(ts, s_range, t_range)
    assert not patch.periodic_u and patch.knots_u[0] == s_range[0] and patch.knots_v[-1] == t_range[1]
    u, v = rng.uniform(*s_range, 1000), rng.uniform(*t_range, 1000)
    wrapped = s_start + np.mod(u - s_start, ts.mesh.s_period)
    assert np.abs(patch.evaluate(u, v).points - ts.evaluate(wrapped, v).points).max() < 1e-9


def test_region_patch_refuses_what_it_cannot_hold(rng):
    ts = _t_spline(rng, True)
    with pytest.raises(ValueError, match="shorter than the period"):
        region_patch(ts, (0.0, 25.0), (1.0, 2.0))
    with pytest.raises(ValueError, match="inside"):
        region_patch(ts, (0.0, 5.0), (-1.0, 2.0))
    rational = ts.with_control_points(ts.control_points, np.linspace(1.0, 2.0, ts.n_control))
    with pytest.raises(FitError, match="polynomial"):
        tensor_product_form(rational)


def test_region_patch_knots_only_where_elements_break(rng):
    """A rectangle inside one row of elements has no t knot at the t-lines that only other rows' T-junctions
    put there: its exact form has fewer poles than one on every line it crosses."""
    ts = _t_spline(rng, True)
    ext = ts.extraction
    e = int(np.argmax(np.diff(ext.t_bounds, axis=1)[:, 0] * np.diff(ext.s_bounds, axis=1)[:, 0]))
    (s0, s1), (t0, t1) = ext.s_bounds[e], ext.t_bounds[e]
    patch = region_patch(ts, (s0, s1), (t0, t1))
    assert len(patch.knots_u) == len(patch.knots_v) == 8  # one Bezier element: clamped ends only
    u, v = rng.uniform(s0, s1, 500), rng.uniform(t0, t1, 500)
    assert np.abs(patch.evaluate(u, v).points - ts.evaluate(u, v).points).max() < 1e-9


@pytest.mark.parametrize("face_cost", [0.0, 40.0, 1e4])
def test_panel_plan_tiles_the_tube_exactly(rng, face_cost):
    ts = _t_spline(rng, True)
    (s_lo, s_hi), (t_lo, t_hi) = ts.mesh.s_range, ts.mesh.t_range
    cut = float(ts.mesh.t_lines[5])
    plan = panel_plan(ts, t_cuts=(cut,), face_cost=face_cost, t_step=1)
    area = sum((s1 - s0) * (t1 - t0) for s0, s1, t0, t1 in plan)
    assert area == pytest.approx((s_hi - s_lo) * (t_hi - t_lo), rel=1e-12)
    assert all(s1 - s0 < ts.mesh.s_period for s0, s1, _, _ in plan) and len(plan) >= 2
    assert not any(t0 < cut < t1 for _, _, t0, t1 in plan)  # never across a forced cut
    # every sample lies in one panel, whose exact form gives the T-spline's point there
    s, t = rng.uniform(s_lo, s_hi, 3000), rng.uniform(t_lo, t_hi, 3000)
    owner = np.full(len(s), -1)
    for k, (s0, s1, t0, t1) in enumerate(plan):
        inside = (s >= s0) & (s < s1) & (t >= t0) & (t < t1)
        assert (owner[inside] < 0).all()
        owner[inside] = k
        if inside.any():
            patch = region_patch(ts, (s0, s1), (t0, t1))
            assert np.abs(patch.evaluate(s[inside], t[inside]).points - ts.evaluate(s[inside], t[inside]).points
                          ).max() < 1e-9
    assert (owner >= 0).all()
    if face_cost >= 1e4:  # faces dear: the fewest the rules allow (two per strip, strips only at the cut)
        assert len(plan) == 4
