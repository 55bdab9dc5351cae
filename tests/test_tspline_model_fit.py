"""T-spline fitting on known smooth surfaces: least squares with parameter
correction converges as control points are added, and local refinement
reaches a tolerance with fewer control points than whole knot lines."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp

from bonecad.settings import Settings
from bonecad.splines.tspline import TSpline, check_suitability
from bonecad.splines.tspline.fit import (
    fit_adaptive,
    initial_parameters,
    project_points,
    solve_control_points,
)
from bonecad.tspline_model.model import tolerances

#: the shipped [tspline] settings as fit tolerances (the tests change a few)
DEFAULT_TOLERANCES = tolerances(Settings.load().tspline)

RADIUS, LENGTH = 10.0, 60.0
PERIOD = 2 * np.pi * RADIUS  # s in mm of arc at the nominal radius


def cylinder(n_s: int, n_t: int) -> TSpline:
    """A coarse tensor-product tube (the starting surface), s periodic."""
    th = 2 * np.pi * np.arange(n_s) / n_s
    z = np.linspace(0.0, LENGTH, n_t + 2)
    cp = np.stack(
        [RADIUS * np.cos(th)[:, None] + 0 * z, RADIUS * np.sin(th)[:, None] + 0 * z,
         np.broadcast_to(z, (n_s, n_t + 2))],
        axis=-1,
    )
    return TSpline.from_grid(np.arange(n_s) * PERIOD / n_s, np.linspace(0.0, LENGTH, n_t), cp, s_period=PERIOD)


def ellipsoid_band(n: int, rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points of an ellipsoid band (semi-axes 12, 8, 45 mm; |z| <= 30 mm), with (s, t) guesses."""
    th = rng.uniform(0, 2 * np.pi, n)
    t = rng.uniform(0, LENGTH, n)
    z = t - LENGTH / 2
    scale = np.sqrt(1 - (z / 45.0) ** 2)
    pts = np.stack([12.0 * scale * np.cos(th), 8.0 * scale * np.sin(th), t], axis=1)
    return pts, th / (2 * np.pi) * PERIOD, t


def bumpy_tube(n: int, rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A tube with two small, well separated bumps: detail a tensor product must pay for everywhere."""
    th = rng.uniform(0, 2 * np.pi, n)
    z = rng.uniform(0, LENGTH, n)
    r = RADIUS + 1.2 * np.exp(-((th - 1.0) ** 2) * 30 - (z - 15.0) ** 2 / 6) + 1.2 * np.exp(
        -((th - 4.0) ** 2) * 30 - (z - 45.0) ** 2 / 6
    )
    return np.stack([r * np.cos(th), r * np.sin(th), z], axis=1), th / (2 * np.pi) * PERIOD, z


def test_least_squares_error_falls_as_control_points_are_added():
    rng = np.random.default_rng(0)
    pts, s, t = ellipsoid_band(6000, rng)
    errors = []
    for n_s, n_t in ((6, 3), (10, 5), (16, 8)):
        ts = cylinder(n_s, n_t)
        ss, tt = s, t
        for _ in range(3):  # parameter correction by projection
            ts = solve_control_points(ts, ss, tt, pts, fairness=1e-6)
            ss, tt, dist = project_points(ts, pts, ss, tt)
        errors.append(float(np.sqrt(np.mean(dist**2))))
    assert errors[0] > 3 * errors[1] > 9 * errors[2]
    assert errors[2] < 2e-3  # mm, on a 24 mm wide band


def test_projection_finds_the_closest_point():
    rng = np.random.default_rng(1)
    ts = cylinder(12, 6)
    pts, s, t = ellipsoid_band(2000, rng)
    ts = solve_control_points(ts, s, t, pts, fairness=1e-6)
    probe = pts + rng.normal(0, 0.3, pts.shape)
    s0, t0, d0 = initial_parameters(ts, probe, grid=(128, 128))
    # the residual is normal to the surface (first-order optimality) ...
    sample = ts.evaluate(s0, t0, order=1)
    r = probe - sample.points
    inside = (t0 > 1e-6) & (t0 < LENGTH - 1e-6)
    cos_s = np.abs(np.einsum("ij,ij->i", r, sample.du)) / (np.linalg.norm(sample.du, axis=1) * np.maximum(d0, 1e-12))
    assert np.percentile(cos_s[inside & (d0 > 1e-3)], 99) < 1e-4
    # ... and no grid sample is closer than the projected point
    gs, gt = np.meshgrid(np.linspace(0, PERIOD, 400), np.linspace(0, LENGTH, 200), indexing="ij")
    dense = ts.evaluate(gs.ravel(), gt.ravel()).points
    from scipy.spatial import cKDTree

    dg, _ = cKDTree(dense).query(probe)
    assert np.all(d0 <= dg + 1e-9)


@pytest.mark.parametrize("tol_mm", [0.02])
def test_local_refinement_needs_fewer_control_points_than_a_tensor_product(tol_mm):
    rng = np.random.default_rng(2)
    pts, s, t = bumpy_tube(12000, rng)
    tol = replace(DEFAULT_TOLERANCES, share_within=(0.99, tol_mm), max_deviation_mm=2.5 * tol_mm, rms_mm=tol_mm / 2,
                        min_element_mm=0.05, max_rounds=8, mark_fraction=0.6)
    local = fit_adaptive(cylinder(8, 4), pts, s=s, t=t, tolerances=tol, fairness=1e-6, mode="local")
    glob = fit_adaptive(cylinder(8, 4), pts, s=s, t=t, tolerances=tol, fairness=1e-6, mode="global")
    assert local.converged and glob.converged, (local.stopped, glob.stopped)
    for res in (local, glob):
        assert res.stats.share_within >= 0.99 and res.stats.max_mm <= 2.5 * tol_mm
        # the history's error falls while control points grow
        counts = [h.control_points for h in res.history]
        assert counts == sorted(counts) and res.history[-1].rms_mm < res.history[0].rms_mm / 5
    assert check_suitability(local.tspline.mesh).suitable
    assert not (local.tspline.mesh.t_edges.all() and local.tspline.mesh.s_edges.all())  # T-junctions
    assert glob.tspline.mesh.t_edges.all() and glob.tspline.mesh.s_edges.all()  # a tensor product
    assert local.tspline.n_control <= 0.75 * glob.tspline.n_control, (local.tspline.n_control, glob.tspline.n_control)


def test_budget_stops_refinement_and_says_so():
    rng = np.random.default_rng(3)
    pts, s, t = bumpy_tube(4000, rng)
    tol = replace(DEFAULT_TOLERANCES, share_within=(0.99, 0.001), max_deviation_mm=0.002, rms_mm=0.0005,
                  max_control_points=150)
    rounds = []
    res = fit_adaptive(cylinder(8, 4), pts, s=s, t=t, tolerances=tol, fairness=1e-6,
                       progress=lambda round_, stats: rounds.append((round_, stats)))
    assert not res.converged
    assert "budget (150)" in res.stopped
    assert res.tspline.n_control <= 150
    # the progress callback saw every round, in order, with its statistics
    assert rounds == list(enumerate(res.history)) and len(rounds) >= 2


def test_local_noise_is_the_rms_residual_of_each_points_own_quadric(rng):
    """The batched local noise against the definition, point by point: the RMS residual of the least-squares
    quadric height field over the point's nearest neighbours in their principal axes."""
    from scipy.spatial import cKDTree

    from bonecad.splines.tspline.fit import local_noise_mm

    pts, _, _ = ellipsoid_band(40000, rng)  # more than two of the batches
    pts = pts + rng.normal(0.0, 0.05, pts.shape)
    noise = local_noise_mm(pts, neighbours=30)
    _, idx = cKDTree(pts).query(pts, k=30)
    for i in rng.choice(len(pts), 25, replace=False):
        q = pts[idx[i]] - pts[idx[i]].mean(axis=0)
        axes = np.linalg.eigh(q.T @ q)[1]  # ascending: the normal first
        z, x, y = (q @ axes).T
        design = np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])
        residual = z - design @ np.linalg.lstsq(design, z, rcond=None)[0]
        assert noise[i] == pytest.approx(np.sqrt(np.mean(residual**2)), rel=1e-6)
    assert 0.03 < np.median(noise) < 0.06  # the 0.05 mm of noise, less what a quadric of 30 points absorbs
    # near some points only: the same scatter, their neighbours still among all points
    some = rng.choice(len(pts), 3000, replace=False)
    np.testing.assert_allclose(local_noise_mm(pts, neighbours=30, at=some), noise[some], rtol=1e-9)


def test_the_noise_level_of_a_sample_of_points_is_that_of_all(rng):
    """The noise level's quantile over every 4th point ([tspline] noise_level_stride) lies within 1 % of the
    quantile over all points, on a surface whose noise varies from place to place."""
    from bonecad.splines.tspline.fit import noise_level_mm

    pts, _, t = ellipsoid_band(40000, rng)
    pts = pts + rng.normal(0.0, 1.0, pts.shape) * (0.02 + 0.08 * t / t.max())[:, None]
    area = np.full(len(pts), 2.0)
    every = noise_level_mm(pts, area, radius_mm=4.0, quantile=0.25)
    assert noise_level_mm(pts, area, radius_mm=4.0, quantile=0.25, stride=4) == pytest.approx(every, rel=0.01)


def test_staircase_is_recognised_and_stops_refinement_at_its_noise():
    from bonecad.splines.tspline.fit import local_noise_mm, voxel_step_mm

    rng = np.random.default_rng(4)
    pts, s, t = ellipsoid_band(20000, rng)
    assert voxel_step_mm(pts) == 0.0  # smooth samples: no lattice
    # a 1 mm voxel mask's surface: vertices on the half-voxel lattice
    stair = np.round(pts / 0.5) * 0.5
    assert voxel_step_mm(stair) == pytest.approx(1.0)
    noise = local_noise_mm(stair, voxel_mm=voxel_step_mm(stair))
    assert noise.min() >= 1.0 / np.sqrt(12) - 1e-12
    tol = replace(DEFAULT_TOLERANCES, share_within=(0.99, 0.1), max_deviation_mm=1.0, rms_mm=0.05,
                  max_control_points=5000,
                        min_element_mm=0.05, max_rounds=8, mark_fraction=0.6)
    free = fit_adaptive(cylinder(8, 4), stair, s=s, t=t, tolerances=tol, fairness=1e-6)
    aware = fit_adaptive(cylinder(8, 4), stair, s=s, t=t, tolerances=tol, fairness=1e-6, noise=noise)
    assert not aware.converged and "up to the data's noise" in aware.stopped, aware.stopped
    assert aware.tspline.n_control < free.tspline.n_control / 2, (aware.tspline.n_control, free.tspline.n_control)
    assert aware.stats.max_mm <= 1.0


def test_fairness_blocks_are_the_exact_thin_plate_energy():
    from bonecad.splines.tspline import refine_elements
    from bonecad.splines.tspline.fit import fairness_blocks

    rng = np.random.default_rng(5)
    pts, s, t = bumpy_tube(3000, rng)
    ts = cylinder(8, 4)
    ts = refine_elements(ts, [3, 9, 17]).tspline
    ts = solve_control_points(ts, s, t, pts, fairness=1e-6)
    q = ts.bezier_points[0].reshape(-1, 16, 3)
    energy = np.einsum("eic,eij,ejc->", q, fairness_blocks(ts), q)
    # reference: 6-point Gauss per direction on every element, from the surface's derivatives
    ext = ts.extraction
    g, gw = np.polynomial.legendre.leggauss(6)
    g, gw = 0.5 * (g + 1), 0.5 * gw
    hs, ht = np.diff(ext.s_bounds, axis=1)[:, 0], np.diff(ext.t_bounds, axis=1)[:, 0]
    ss = (ext.s_bounds[:, :1, None] + g[None, :, None] * hs[:, None, None] + 0 * g[None, None, :]).ravel()
    tt = (ext.t_bounds[:, :1, None] + 0 * g[None, :, None] + g[None, None, :] * ht[:, None, None]).ravel()
    d = ts.evaluate(ss, tt, order=2)
    dens = (np.sum(d.duu**2, 1) + 2 * np.sum(d.duv**2, 1) + np.sum(d.dvv**2, 1)).reshape(-1, 6, 6)
    reference = np.einsum("eij,i,j,e->", dens, gw, gw, hs * ht)
    assert energy == pytest.approx(reference, rel=1e-9)


def test_split_direction_follows_the_residual():
    from bonecad.splines.tspline.fit import _split_axes

    rng = np.random.default_rng(6)
    n = 4000
    elem = rng.integers(0, 3, n)
    u, v = rng.random(n), rng.random(n)
    # element 0 misses detail along u, element 1 along v, element 2 along both
    res = np.where(elem == 0, np.sin(6 * u), np.where(elem == 1, np.sin(6 * v), np.sin(6 * u) + np.sin(6 * v)))
    halvable = np.ones((3, 2), dtype=bool)
    apart = sp.csr_matrix((3, 3))  # no two of them neighbours
    axes = _split_axes(np.arange(3), elem, u, v, res, np.ones(n), halvable, 2.0, apart)
    assert axes.tolist() == [[True, False], [False, True], [True, True]]
    # isotropic setting: always both; a direction below the size limit is dropped
    assert _split_axes(np.arange(3), elem, u, v, res, np.ones(n), halvable, np.inf, apart).all()
    halvable[2, 0] = False
    assert _split_axes(np.arange(3), elem, u, v, res, np.ones(n), halvable, 2.0, apart)[2].tolist() == [False, True]


def test_neighbouring_marked_elements_share_one_split_direction():
    from bonecad.splines.tspline import refine_elements
    from bonecad.splines.tspline.fit import _marked_adjacency, _split_axes

    ts = cylinder(12, 6)
    ext = ts.extraction
    i0, _, j0, _ = ext.index_bounds.T
    cell = {(int(a), int(b)): e for e, (a, b) in enumerate(zip(i0, j0))}
    lo_j = int(j0.min())
    # a (first s-cell) and b (last s-cell) are neighbours across the seam, c on top of a, d far away
    a, b, c, d = cell[0, lo_j + 2], cell[11, lo_j + 2], cell[0, lo_j + 3], cell[6, lo_j + 4]
    marked = np.array([a, b, c, d])
    adj = _marked_adjacency(ext, marked).toarray()
    assert adj.tolist() == [[0, 1, 1, 0], [1, 0, 0, 0], [1, 0, 0, 0], [0, 0, 0, 0]]
    rng = np.random.default_rng(7)
    n = 8000
    elem = marked[rng.integers(0, 4, n)]
    u, v = rng.random(n), rng.random(n)
    # a and d miss detail along u, b (strongly) and c along v: the cluster {a, b, c} prefers v
    res = np.select([elem == a, elem == b, elem == c], [np.sin(6 * u), 3 * np.sin(6 * v), np.sin(6 * v)],
                    np.sin(6 * u))
    halvable = np.ones((ext.n_elements, 2), dtype=bool)
    axes = _split_axes(marked, elem, u, v, res, np.ones(n), halvable, 1.0, sp.csr_matrix(adj))
    assert axes.tolist() == [[False, True]] * 3 + [[True, False]]
    # one direction for the pair: their new t-lines continue into each other, no crossing extensions to close
    own = np.array([[True, False], [False, True]])
    shared = refine_elements(ts, [a, b], axes[:2])
    mixed = refine_elements(ts, [a, b], own)
    assert shared.added < mixed.added, (shared.added, mixed.added)


def test_once_share_and_rms_hold_only_points_beyond_the_maximum_ask_for_refinement():
    from bonecad.splines.tspline.fit import _marked_elements

    ts = cylinder(12, 6)
    rng = np.random.default_rng(2)
    n = 20000
    s, t = rng.uniform(0, PERIOD, n), rng.uniform(0, LENGTH, n)
    elem, _, _ = ts.extraction.locate(s, t)
    tol = replace(DEFAULT_TOLERANCES, share_within=(0.99, 0.25), max_deviation_mm=1.0, rms_mm=0.1, mark_fraction=0.6,
                        mark_deficit_factor=2.0, min_element_mm=0.1)
    distance = np.full(n, 0.05)
    distance[: n // 200] = 0.4  # 0.5 % beyond 0.25 mm: the share holds
    distance[n // 200] = 1.5  # one point beyond the maximum
    marked, _ = _marked_elements(ts, elem, distance, np.ones(n), tol)
    assert marked.tolist() == [elem[n // 200]]
    # with the share missed, the elements holding the points beyond 0.25 mm are marked too
    distance[: n // 20] = 0.4
    marked, _ = _marked_elements(ts, elem, distance, np.ones(n), tol)
    assert elem[n // 200] in marked and len(marked) > 1
    # ... unless the share holds up to the data's noise: then again only the point beyond the maximum asks
    distance[n // 200] = 1.5
    marked, _ = _marked_elements(ts, elem, distance, np.ones(n), tol, stalled=distance < 1.0, share_held=True)
    assert marked.tolist() == [elem[n // 200]]


def test_staircase_with_a_fold_no_element_can_follow_stops_at_its_noise_and_says_so():
    """A staircase with a fold (points 1.3 mm out and 1.3 mm in at one place: no surface comes within the
    1 mm maximum of both, however fine): once the share holds up to the noise, only the points beyond the
    maximum ask for refinement, and when their elements are at the size limit the fit stops at the noise."""
    from bonecad.splines.tspline.fit import local_noise_mm, voxel_step_mm

    rng = np.random.default_rng(4)
    pts, s, t = ellipsoid_band(20000, rng)
    stair = np.round(pts / 0.5) * 0.5
    fold = np.flatnonzero(np.hypot(s - 30.0, t - 30.0) < 0.6)
    normal = pts[fold] * np.array([1.0 / 144, 1.0 / 64, 0.0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    stair[fold] = pts[fold] + normal * np.where(np.arange(len(fold)) % 2, 1.3, -1.3)[:, None]
    noise = local_noise_mm(stair, voxel_mm=voxel_step_mm(stair))
    tol = replace(DEFAULT_TOLERANCES, share_within=(0.99, 0.1), max_deviation_mm=1.0, rms_mm=0.05,
                  max_control_points=5000, min_element_mm=0.5, max_rounds=10)
    res = fit_adaptive(cylinder(8, 4), stair, s=s, t=t, tolerances=tol, fairness=1e-6, noise=noise)
    assert len(fold) >= 4 and res.stats.max_mm > 1.0
    assert "up to the data's noise" in res.stopped and "size limit" in res.stopped, res.stopped
    assert len(res.history) < tol.max_rounds + 1


def test_rough_data_stop_at_their_noise_level_once_share_and_rms_hold_and_say_so():
    """Noise of 0.05 mm RMS and six lone spikes 1.4 mm out: once the share and the RMS hold with the RMS
    residual at the data's noise level, the spikes beyond the 1 mm maximum are taken for noise (discrepancy
    principle); without a noise level the fit chases them to the round limit."""
    from bonecad.splines.tspline.fit import noise_level_mm

    rng = np.random.default_rng(6)
    pts, s, t = ellipsoid_band(20000, rng)
    radial = pts * np.array([1.0 / 144, 1.0 / 64, 0.0])
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    area = np.full(len(pts), 2 * np.pi * RADIUS * LENGTH / len(pts))
    noisy = pts + radial * rng.normal(0.0, 0.05, len(pts))[:, None]
    # the noise adds to the smooth band's quadric misfit at 6 mm (lower quartile, measured 0.025 -> 0.058 mm)
    def level(points: np.ndarray) -> float:
        return noise_level_mm(points, area, radius_mm=6.0, quantile=0.25)

    assert level(noisy) > level(pts) + 0.025
    spikes = rng.choice(len(pts), 6, replace=False)
    noisy[spikes] += radial[spikes] * 1.4
    tol = replace(DEFAULT_TOLERANCES, share_within=(0.99, 0.25), max_deviation_mm=1.0, rms_mm=0.1,
                  max_control_points=5000, min_element_mm=0.5, max_rounds=8)
    chased = fit_adaptive(cylinder(8, 4), noisy, s=s, t=t, tolerances=tol, fairness=1e-6)
    stopped = fit_adaptive(cylinder(8, 4), noisy, s=s, t=t, tolerances=tol, fairness=1e-6, noise_level=0.1)
    assert "round limit" in chased.stopped and chased.stats.max_mm > 1.0  # measured 283 control points
    note = stopped.stopped
    assert note.startswith("stopped at the data's noise") and "6 points beyond 1.0 mm" in note, note
    assert stopped.tspline.n_control < chased.tspline.n_control / 2  # measured 48
    assert stopped.stats.share_within >= 0.99 and stopped.stats.rms_mm <= 0.1
