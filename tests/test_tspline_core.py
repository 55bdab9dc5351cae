"""T-spline core: T-mesh validation, blending functions, extraction, continuity, JSON.

The test surfaces are tubes (s periodic round the axis, t clamped along it),
the shape of a long bone's shaft, with non-uniform knots and random
control-point noise so that no symmetry hides an indexing error.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bonecad.errors import InputError
from bonecad.splines.tspline import TMesh, TSpline, check_suitability, from_dict, load, refine_elements, save, to_dict


def tube(n_s: int = 12, n_t: int = 8, *, seed: int = 0, rational: bool = False, period: float = 2.0) -> TSpline:
    """A wobbly tube: s periodic with random knot spacing, t clamped, mm-sized."""
    rng = np.random.default_rng(seed)
    gaps = rng.uniform(0.5, 1.5, n_s)
    s_knots = np.concatenate([[0.0], np.cumsum(gaps)[:-1]]) * period / gaps.sum()
    t_knots = np.concatenate([[0.0], np.cumsum(rng.uniform(0.5, 1.5, n_t - 1))])
    theta = 2 * np.pi * np.arange(n_s) / n_s
    z = np.linspace(0.0, 100.0, n_t + 2)
    r = 15.0 + rng.normal(0.0, 1.0, (n_s, n_t + 2))
    cp = np.stack([r * np.cos(theta)[:, None], r * np.sin(theta)[:, None], np.broadcast_to(z, r.shape)], axis=-1)
    cp = cp + rng.normal(0.0, 0.5, cp.shape)
    w = rng.uniform(0.6, 1.6, (n_s, n_t + 2)) if rational else None
    return TSpline.from_grid(s_knots, t_knots, cp, w, s_period=period)


def t_tube(seed: int = 0, *, rational: bool = False) -> TSpline:
    """A tube with T-junctions: a few elements refined locally (incl. one at the seam)."""
    ts = tube(seed=seed, rational=rational)
    ext = ts.extraction
    seam = int(np.flatnonzero(ext.index_bounds[:, 0] == 0)[3])
    return refine_elements(ts, [seam, 30, 31, 50]).tspline


def random_params(ts: TSpline, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = ts.mesh.s_range
    t0, t1 = ts.mesh.t_range
    return rng.uniform(lo - 0.5, hi + 0.5, n), rng.uniform(t0, t1, n)


def size(ts: TSpline) -> float:
    return float(np.ptp(ts.control_points, axis=0).max())


# ---------------------------------------------------------------- blending functions
@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_partition_of_unity_with_t_junctions(seed):
    ts = t_tube(seed % 7)
    assert check_suitability(ts.mesh).suitable
    rng = np.random.default_rng(seed)
    s, t = random_params(ts, 300, rng)
    b = ts.blending_values(s, t)
    assert np.abs(b.sum(axis=1) - 1.0).max() < 1e-12
    assert b.min() >= -1e-15


def test_partition_of_unity_across_the_seam():
    ts = t_tube(1)
    lo, hi = ts.mesh.s_range
    t = np.linspace(*ts.mesh.t_range, 50)
    for s in (lo, lo + 1e-12, hi - 1e-12, hi, lo - 1e-3, hi + 1e-3):
        b = ts.blending_values(np.full_like(t, s), t)
        assert np.abs(b.sum(axis=1) - 1.0).max() < 1e-12
    # the seam is no boundary: same point from both sides
    a = ts.evaluate(np.full_like(t, hi - 1e-13), t).points
    c = ts.evaluate(np.full_like(t, lo), t).points
    assert np.abs(a - c).max() < 1e-9 * size(ts)


def test_ray_casting_gives_clamped_knots_at_the_ends():
    ts = tube()
    mesh = ts.mesh
    _, t_idx = mesh.anchor_knots
    tk = mesh.t_lines[t_idx]
    t0, t1 = mesh.t_range
    first_row = mesh.anchors[:, 1] == 2
    assert np.all(tk[first_row][:, :4] == t0)  # [t0, t0, t0, t0, t1]
    assert np.all(tk[first_row][:, 4] > t0)
    last_row = mesh.anchors[:, 1] == mesh.shape[1] - 3
    assert np.all(tk[last_row][:, 1:] == t1)


@pytest.mark.parametrize("rational", [False, True])
def test_bezier_patches_reproduce_direct_evaluation(rational):
    ts = t_tube(2, rational=rational)
    rng = np.random.default_rng(3)
    s, t = random_params(ts, 2000, rng)
    direct = ts.evaluate_direct(s, t)
    assert np.abs(ts.evaluate(s, t).points - direct).max() < 1e-9 * size(ts)
    # the sparse basis matrix gives the same surface
    m = ts.basis_matrix(s, t)
    assert np.abs(m @ ts.control_points - direct).max() < 1e-9 * size(ts)
    assert np.diff(m.indptr).max() <= 16


def test_bezier_points_come_from_the_extraction_operator():
    ts = t_tube(4)
    ext = ts.extraction
    e = 17
    anchors, c = ext.element_operator(e)
    q = c.T @ ts.control_points[anchors]  # polynomial: weights 1
    assert np.allclose(q.reshape(4, 4, 3), ts.bezier_points[0][e], atol=1e-12 * size(ts))
    assert np.allclose(c.sum(axis=0), 1.0)  # Bernstein coefficients of a partition of unity


def test_derivatives_match_finite_differences():
    ts = t_tube(5, rational=True)
    rng = np.random.default_rng(5)
    s, t = random_params(ts, 200, rng)
    h = 1e-6
    d = ts.evaluate(s, t, order=2)
    fd_s = (ts.evaluate(s + h, t).points - ts.evaluate(s - h, t).points) / (2 * h)
    fd_t = (ts.evaluate(s, t + h).points - ts.evaluate(s, t - h).points) / (2 * h)
    t_in = (t > ts.mesh.t_range[0] + 2 * h) & (t < ts.mesh.t_range[1] - 2 * h)
    scale = np.abs(d.du).max()
    assert np.abs(fd_s - d.du).max() < 1e-5 * scale
    assert np.abs(fd_t - d.dv)[t_in].max() < 1e-5 * np.abs(d.dv).max()
    fd_st = (ts.evaluate(s + h, t, order=1).dv - ts.evaluate(s - h, t, order=1).dv) / (2 * h)
    assert np.abs(fd_st - d.duv)[t_in].max() < 1e-4 * np.abs(d.duv).max()
    for (a, b), ds, dt in (((1, 0), 1, 0), ((0, 1), 0, 1), ((2, 0), 2, 0), ((1, 1), 1, 1), ((0, 2), 0, 2)):
        ref = {(1, 0): d.du, (0, 1): d.dv, (2, 0): d.duu, (1, 1): d.duv, (0, 2): d.dvv}[(a, b)]
        got = ts.basis_matrix(s, t, ds=ds, dt=dt) @ ts.control_points
        assert np.abs(got - ref).max() < 1e-9 * np.abs(ref).max()


def _one_sided(ts: TSpline, s, t, eps_s, eps_t):
    lo = ts.evaluate(s - eps_s, t - eps_t, order=2)
    hi = ts.evaluate(s + eps_s, t + eps_t, order=2)
    return lo, hi


@pytest.mark.parametrize("rational", [False, True])
def test_c2_across_interior_element_boundaries_and_the_seam(rational):
    ts = t_tube(6, rational=rational)
    ext = ts.extraction
    rng = np.random.default_rng(6)
    eps = 1e-10
    lo, hi = ts.mesh.s_range
    # s-boundaries (lines of constant s), the seam included
    t_in = ext.t_bounds[:, 0] + rng.uniform(0.1, 0.9, ext.n_elements) * np.diff(ext.t_bounds, axis=1)[:, 0]
    s_b = ext.s_bounds[:, 1]
    left, right = _one_sided(ts, s_b, t_in, eps, 0.0)
    assert np.any(s_b >= hi)  # elements that end on the seam
    # t-boundaries, interior only
    inner = ext.t_bounds[:, 1] < ts.mesh.t_range[1]
    s_in = ext.s_bounds[inner, 0] + rng.uniform(0.1, 0.9, inner.sum()) * np.diff(ext.s_bounds[inner], axis=1)[:, 0]
    below, above = _one_sided(ts, s_in, ext.t_bounds[inner, 1], 0.0, eps)
    for a, b in ((left, right), (below, above)):
        for name in ("points", "du", "dv", "duu", "duv", "dvv"):
            x, y = getattr(a, name), getattr(b, name)
            scale = np.abs(getattr(left, name)).max()
            assert np.abs(x - y).max() < 1e-6 * scale, name


# ---------------------------------------------------------------- T-mesh rules
def _grid_mesh() -> TMesh:
    return TMesh.grid(np.arange(12.0), np.arange(10.0))


def test_non_suitable_mesh_is_detected_with_the_offending_pairs():
    mesh = _grid_mesh()
    s_e, t_e = mesh.s_edges.copy(), mesh.t_edges.copy()
    i, j = 8, 8  # grid point (s=5, t=5): lines 8, 8 (3 clamped end lines before the knot 0)
    t_e[i, j - 1 : j + 1] = False  # vertical line broken around the point
    s_e[j, i - 1 : i + 1] = False  # horizontal line broken around it: four T-junctions facing it
    bad = mesh.with_edges(s_e, t_e)
    report = check_suitability(bad)
    assert not report.suitable
    assert len(report.junctions.points) == 4
    assert len(report.pairs) == 4  # each horizontal extension meets each vertical one
    assert np.allclose(report.pair_params[:, 0], [[4.0, 5.0]] * 2 + [[6.0, 5.0]] * 2)
    assert "meets" in report.describe()
    # one broken line alone is analysis-suitable
    s_e2 = mesh.s_edges.copy()
    s_e2[j, i - 1 : i + 1] = False
    assert check_suitability(mesh.with_edges(s_e2, mesh.t_edges)).suitable


def test_invalid_meshes_are_rejected_with_clear_errors():
    mesh = _grid_mesh()
    i, j = 8, 8
    s_e, t_e = mesh.s_edges.copy(), mesh.t_edges.copy()
    s_e[j, i - 1 : i + 1] = False
    t_e[i, j - 1] = False
    with pytest.raises(ValueError, match="ends in the open"):
        mesh.with_edges(s_e, t_e)
    s_e, t_e = mesh.s_edges.copy(), mesh.t_edges.copy()
    s_e[j, i] = False
    t_e[i, j] = False
    with pytest.raises(ValueError, match="L-shaped corner"):
        mesh.with_edges(s_e, t_e)
    t_e = mesh.t_edges.copy()
    t_e[i, j : mesh.shape[1] - 4] = False  # the line stops, its end-strip part stays
    with pytest.raises(ValueError, match="end strip"):
        mesh.with_edges(mesh.s_edges, t_e)
    with pytest.raises(ValueError, match="increase strictly"):
        TMesh.grid([0.0, 2.0, 1.0, 3.0], [0.0, 1.0])
    with pytest.raises(ValueError, match="at least 4"):
        TMesh.grid([0.0, 1.0, 2.0], [0.0, 1.0], s_period=3.0)
    with pytest.raises(ValueError, match=r"expected \(12, 4, 3\)"):
        TSpline.from_grid(np.arange(12.0), [0.0, 1.0], np.zeros((12, 5, 3)), s_period=12.0)
    ts = tube()
    with pytest.raises(ValueError, match="weights"):
        TSpline(ts.mesh, ts.control_points, -ts.weights)
    with pytest.raises(ValueError, match="outside the parameter range"):
        ts.evaluate([0.0], [ts.mesh.t_range[1] + 1.0])


def test_open_s_direction_is_a_clamped_bspline_patch():
    rng = np.random.default_rng(8)
    ts = TSpline.from_grid([0.0, 0.5, 1.5, 2.0], [0.0, 1.0, 3.0], rng.normal(size=(6, 5, 3)))
    s, t = rng.uniform(0, 2, 500), rng.uniform(0, 3, 500)
    b = ts.blending_values(s, t)
    assert np.abs(b.sum(axis=1) - 1).max() < 1e-12
    assert np.abs(ts.evaluate(s, t).points - ts.evaluate_direct(s, t)).max() < 1e-12
    corner = ts.evaluate([0.0, 2.0], [0.0, 3.0]).points  # clamped: corners interpolate
    grid = ts.control_points.reshape(5, 6, 3)
    assert np.allclose(corner, [grid[0, 0], grid[-1, -1]], atol=1e-12)


# ---------------------------------------------------------------- JSON
def test_json_round_trip_is_exact(tmp_path):
    ts = t_tube(9, rational=True)
    back = load(save(ts, tmp_path / "ts.json"))
    for name in ("s_lines", "t_lines", "s_edges", "t_edges"):
        assert np.array_equal(getattr(back.mesh, name), getattr(ts.mesh, name))
    assert back.mesh.s_period == ts.mesh.s_period
    assert np.array_equal(back.control_points, ts.control_points)
    assert np.array_equal(back.weights, ts.weights)
    rng = np.random.default_rng(9)
    s, t = random_params(ts, 500, rng)
    assert np.array_equal(back.evaluate(s, t).points, ts.evaluate(s, t).points)


def test_json_rejects_malformed_documents(tmp_path):
    data = to_dict(tube())
    with pytest.raises(InputError, match="version"):
        from_dict({**data, "version": 99})
    with pytest.raises(InputError, match="outside the grid"):
        from_dict({**data, "t_edges": data["t_edges"] + [[999, 0, 1]]})
    with pytest.raises(InputError, match="anchors"):
        from_dict({**data, "control_points": data["control_points"][:-1], "weights": data["weights"][:-1]})
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(InputError, match="bad.json"):
        load(tmp_path / "bad.json")
