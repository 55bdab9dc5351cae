"""Deviation analysis on shapes whose distances are known in closed form."""
from __future__ import annotations

import numpy as np
import pytest

from bonecad.mesh.closest import TriangleLocator
from bonecad.analysis.deviation import sample_shape, sample_surface, shape_deviation, signed_distance_to_shape
from bonecad.analysis.statistics import band_edges, deviation_stats, histogram, weighted_percentiles
from bonecad.occ.tessellate import tessellate
from bonecad.errors import KernelError
from tests.defaults import BANDS_MM, SETTINGS, TESSELLATION
from dataclasses import replace


RADIUS = 10.0


def _nurbs(shape):
    """The shape with every face converted to a (native) B-spline surface."""
    from OCP.BRepBuilderAPI import BRepBuilderAPI_NurbsConvert

    return BRepBuilderAPI_NurbsConvert(shape, True).Shape()


@pytest.fixture(scope="module")
def sphere():
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeSphere

    return _nurbs(BRepPrimAPI_MakeSphere(RADIUS).Shape())


@pytest.fixture(scope="module")
def sphere_fine(sphere):
    return tessellate(sphere, replace(TESSELLATION, deflection_mm=0.005))


def test_faces_are_native_bspline(sphere):
    from OCP.BRep import BRep_Tool
    from OCP.Geom import Geom_BSplineSurface

    from bonecad.occ.brep import faces

    assert all(isinstance(BRep_Tool.Surface_s(f), Geom_BSplineSurface) for f in faces(sphere))


def test_tessellation_covers_exact_area(sphere_fine):
    exact = sphere_fine.face_area_exact_mm2.sum()
    assert exact == pytest.approx(4 * np.pi * RADIUS**2, rel=1e-5)
    assert sphere_fine.face_area_mesh_mm2.sum() == pytest.approx(exact, rel=5e-3)
    # nodes lie on the sphere, normals point outwards
    assert np.abs(np.linalg.norm(sphere_fine.vertices, axis=1) - RADIUS).max() < 1e-9
    radial = sphere_fine.vertices / RADIUS
    away_from_poles = np.abs(radial[:, 2]) < 1 - 1e-9  # no surface normal at a pole
    assert np.einsum("ij,ij->i", radial, sphere_fine.normals)[away_from_poles].min() > 0.999


def test_coverage_check_refuses_a_short_tessellation(sphere):
    # a chordal tessellation is always short of the exact area; demanding a
    # surplus makes the check fire, as a partial cover would
    with pytest.raises(KernelError, match="tessellation covers"):
        tessellate(sphere, replace(TESSELLATION, deflection_mm=0.05, coverage_tolerance=-1e-3, small_face_factor=0.0))


def test_small_curved_faces_get_their_chordal_allowance():
    settings = replace(TESSELLATION, deflection_mm=0.05, coverage_tolerance=0.005, small_face_factor=2.0)
    allowed = settings.allowed_shortfall(np.array([1.0, 0.25, 10000.0]))
    assert allowed[0] == pytest.approx(0.1) and allowed[1] == pytest.approx(0.2)
    assert allowed[2] == pytest.approx(0.005)  # large faces: the plain tolerance, partial covers refused


def test_exact_projection_matches_analytic_sphere(sphere_fine):
    rng = np.random.default_rng(0)
    direction = rng.normal(size=(20000, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    points = direction * (RADIUS + rng.uniform(-2.0, 2.0, len(direction)))[:, None]
    sd = signed_distance_to_shape(points, sphere_fine)
    exact = np.linalg.norm(points, axis=1) - RADIUS
    assert sd.refined.mean() > 0.99  # all but points projecting onto the poles
    assert np.abs(sd.distance_mm - exact)[sd.refined].max() < 1e-8
    # the rest keep the tessellation distance, within the measured chord error
    assert np.abs(sd.distance_mm - exact).max() <= sphere_fine.chord_error_mm.max() + 1e-9


def test_sphere_against_its_own_tessellation_is_at_the_tessellation_bound(sphere):
    """Done-when of issue 4: a B-spline sphere vs its own tessellation."""
    coarse = tessellate(sphere, replace(TESSELLATION, deflection_mm=0.05))
    bound = coarse.chord_error_mm.max()
    result = shape_deviation(coarse.vertices, coarse.triangles, tessellate(sphere, TESSELLATION), edges_mm=BANDS_MM,
                             sample_points=20000)
    fwd = result.mesh_to_cad
    exact = np.linalg.norm(fwd.points, axis=1) - RADIUS
    np.testing.assert_allclose(fwd.deviation_mm, exact, atol=1e-8)
    # chords lie inside: every deviation between -bound and 0, the largest near the bound
    assert fwd.stats.max_inside_mm <= bound + 1e-9
    assert fwd.stats.max_inside_mm >= 0.5 * bound
    assert fwd.stats.max_outside_mm <= 1e-9
    # back: exact sphere points sit outside the chordal mesh, i.e. mesh inside (negative)
    back = result.cad_to_mesh
    np.testing.assert_allclose(np.linalg.norm(back.points, axis=1), RADIUS, atol=1e-9)
    assert back.stats.max_inside_mm <= bound + 1e-9
    assert back.stats.max_outside_mm <= 1e-9
    assert back.stats.area_mm2 == pytest.approx(4 * np.pi * RADIUS**2, rel=1e-5)


def test_vertex_deviation_for_the_colour_map_is_within_the_chord_error(sphere, sphere_fine):
    """Vertices on the exact sphere (distance 0), away from the tessellation's nodes, are measured on
    the tessellation: within its chord error, and not exactly (a picture, not a statistic)."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=RADIUS)
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    result = shape_deviation(vertices, faces, sphere_fine, edges_mm=BANDS_MM, sample_points=2000)
    exact = np.linalg.norm(vertices, axis=1) - RADIUS
    assert np.abs(exact).max() < 1e-9
    error = np.abs(result.vertex_deviation_mm - exact)
    assert error.max() <= sphere_fine.chord_error_mm.max() + 1e-9
    assert error.max() > 1e-4


def test_shape_samples_lie_on_the_exact_surface_with_area_weights(sphere):
    """Caps of a sphere (area 2 pi R h): their weighted share of samples drawn on a coarse tessellation."""
    coarse = tessellate(sphere, replace(TESSELLATION, deflection_mm=0.05))
    count = 100000
    points, weights, on_surface = sample_shape(coarse, count, seed=2)
    assert on_surface.all()
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), RADIUS, atol=1e-9)
    assert weights.sum() == pytest.approx(4 * np.pi * RADIUS**2, rel=1e-5)
    for height in (0.0, 5.0, 9.0):
        share = (RADIUS - height) / (2 * RADIUS)
        got = weights[points[:, 2] > height].sum() / weights.sum()
        assert abs(got - share) <= 4 * np.sqrt(share * (1 - share) / count)  # 4 standard errors


def test_sign_is_positive_for_a_mesh_outside_the_model(sphere, sphere_fine):
    scale = 1.01  # mesh 0.1 mm outside the sphere everywhere
    result = shape_deviation(sphere_fine.vertices * scale, sphere_fine.triangles, sphere_fine, edges_mm=BANDS_MM,
                             sample_points=5000)
    fwd, back = result.mesh_to_cad, result.cad_to_mesh
    assert fwd.stats.mean_mm == pytest.approx(0.1, abs=0.01)
    assert back.stats.mean_mm == pytest.approx(0.1, abs=0.01)
    assert fwd.stats.max_inside_mm < 0 and back.stats.max_inside_mm < 0
    # all of the surface in the band [0.1, 0.2) up to chord effects at 0.05-0.1
    bound = sphere_fine.chord_error_mm.max()
    assert fwd.deviation_mm.max() <= 0.1 + 1e-9
    assert fwd.deviation_mm.min() >= 0.1 - 1.01 * bound - 1e-9
    # so all of the surface lies in the bands [0, 0.1) and [0.1, 0.2)
    edges = fwd.histogram.edges_mm
    zero = int(np.argmin(np.abs(edges)))
    assert fwd.histogram.shares[1 + zero] + fwd.histogram.shares[2 + zero] == pytest.approx(1.0)


def test_cylinder_with_planar_caps():
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeCylinder

    cyl = _nurbs(BRepPrimAPI_MakeCylinder(5.0, 20.0).Shape())
    fine = tessellate(cyl, replace(TESSELLATION, deflection_mm=0.01))
    coarse = tessellate(cyl, replace(TESSELLATION, deflection_mm=0.1))
    result = shape_deviation(coarse.vertices, coarse.triangles, fine, edges_mm=BANDS_MM, sample_points=20000)
    fwd = result.mesh_to_cad
    p = fwd.points
    on_side = (p[:, 2] > 1e-6) & (p[:, 2] < 20 - 1e-6)
    exact_side = np.hypot(p[:, 0], p[:, 1]) - 5.0
    np.testing.assert_allclose(fwd.deviation_mm[on_side], exact_side[on_side], atol=1e-8)
    assert np.abs(fwd.deviation_mm[~on_side]).max() < 1e-8
    assert fwd.stats.max_inside_mm <= coarse.chord_error_mm.max() + 1e-9


def test_chord_error_near_points_is_the_largest_of_the_triangles_within_reach():
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeCylinder

    cyl = _nurbs(BRepPrimAPI_MakeCylinder(5.0, 20.0).Shape())
    settings = replace(TESSELLATION, deflection_mm=0.1)
    every = tessellate(cyl, settings).chord_error_mm
    side = int(np.argmax(every))  # the curved face; the planar caps have no chord error
    assert every[side] > 0 and np.sort(every)[-2] < 1e-9
    # points far from everything reach every triangle: the largest chord error of all
    assert tessellate(cyl, settings).chord_error_near([[100.0, 0.0, 10.0]], [200.0]) == pytest.approx(every[side])
    # a point at the middle of a cap, 0.5 mm above it, reaches only cap triangles
    assert tessellate(cyl, settings).chord_error_near([[0.0, 0.0, 20.5]], [0.5]) < 1e-9
    assert tessellate(cyl, settings).chord_error_near(np.zeros((0, 3)), np.zeros(0)) == 0.0


def test_regions_partition_the_histogram(sphere, sphere_fine):
    def regions(points):
        return np.where(points[:, 2] < -5, "distal", np.where(points[:, 2] > 5, "proximal", "shaft"))

    result = shape_deviation(sphere_fine.vertices * 1.02, sphere_fine.triangles, sphere_fine, edges_mm=BANDS_MM,
                             sample_points=6000, regions=regions)
    fwd = result.mesh_to_cad
    assert set(fwd.region_stats) == {"distal", "shaft", "proximal"}
    total = sum(fwd.region_stats[r].area_mm2 for r in fwd.region_stats)
    assert total == pytest.approx(fwd.stats.area_mm2)
    mixed = sum(fwd.region_histograms[r].shares * fwd.region_stats[r].area_mm2 for r in fwd.region_stats)
    np.testing.assert_allclose(mixed / total, fwd.histogram.shares, atol=1e-12)
    # a z-band of a sphere between -5 and 5 holds half its area (Archimedes)
    assert fwd.region_stats["shaft"].area_mm2 / total == pytest.approx(0.5, abs=0.03)


def test_bad_region_labels_are_refused(sphere, sphere_fine):
    with pytest.raises(ValueError, match="unknown region labels"):
        shape_deviation(sphere_fine.vertices, sphere_fine.triangles, sphere_fine, edges_mm=BANDS_MM,
                        sample_points=100, regions=lambda p: np.full(len(p), "femur"))


def test_closest_points_match_brute_force():
    rng = np.random.default_rng(3)
    # a bumpy open grid surface with a few large triangles (planar cap case)
    n = 30
    x, y = np.meshgrid(np.linspace(0, 10, n), np.linspace(0, 10, n), indexing="ij")
    z = np.sin(x) * np.cos(y)
    vertices = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    idx = np.arange(n * n).reshape(n, n)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], axis=-1).reshape(-1, 4)
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    big = np.array([[0.0, 0.0, 5.0], [40.0, 0.0, 5.0], [0.0, 40.0, 5.0]])
    vertices = np.concatenate([vertices, big])
    tris = np.concatenate([tris, [[n * n, n * n + 1, n * n + 2]]])
    points = rng.uniform([-2, -2, -3], [12, 12, 8], size=(400, 3))
    got = TriangleLocator(vertices, tris).query(points)
    # brute force: every triangle for every point
    from bonecad.mesh.closest import closest_point_on_triangles

    t = vertices[tris]
    rep = np.repeat(points, len(tris), axis=0)
    cp, _ = closest_point_on_triangles(rep, *(np.tile(t[:, k], (len(points), 1)) for k in range(3)))
    brute = np.linalg.norm(rep - cp, axis=1).reshape(len(points), len(tris)).min(axis=1)
    np.testing.assert_allclose(got.distance, brute, atol=1e-12)


def test_closest_points_do_not_depend_on_the_order_they_are_asked_in(sphere_fine):
    """The locator asks its tree in its own (coherent) order: each point's answer is its own, in the caller's
    order; distance() agrees with query()."""
    rng = np.random.default_rng(8)
    points = rng.normal(size=(3000, 3)) * 12.0
    locator = TriangleLocator(sphere_fine.vertices, sphere_fine.triangles)
    got = locator.query(points)
    shuffled = rng.permutation(len(points))
    again = locator.query(points[shuffled])
    np.testing.assert_array_equal(again.triangle, got.triangle[shuffled])
    np.testing.assert_array_equal(again.points, got.points[shuffled])
    np.testing.assert_allclose(locator.distance(points), got.distance, rtol=0, atol=1e-12)
    # the answer of each point alone
    for i in rng.choice(len(points), 20, replace=False):
        assert locator.query(points[i:i + 1]).triangle[0] == got.triangle[i]


def test_sampling_is_deterministic_and_area_weighted():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [10, 0, 0], [13, 0, 0], [10, 3, 0]], float)
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    a = sample_surface(vertices, faces, 20000, seed=5)
    b = sample_surface(vertices, faces, 20000, seed=5)
    np.testing.assert_array_equal(a.points, b.points)
    assert np.mean(a.triangle == 1) == pytest.approx(9 / 10, abs=0.01)
    assert a.weights.sum() == pytest.approx(5.0)


def test_stratified_samples_estimate_a_share_with_less_noise():
    """A sphere's cap above z = 0.3 holds 35 % of its area: over 12 seeds the stratified samples' share of it
    lies within 0.3 binomial standard errors of it (independent draws: one standard error, 1.1 points)."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=5)
    order = np.random.default_rng(0).permutation(len(sphere.faces))  # a face order with no spatial sense
    vertices, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces)[order]
    count = 2000
    shares = [np.mean(sample_surface(vertices, faces, count, seed=seed).points[:, 2] > 0.3) for seed in range(12)]
    exact = sphere.area_faces[sphere.triangles_center[:, 2] > 0.3].sum() / sphere.area
    standard_error = np.sqrt(exact * (1 - exact) / count)
    assert abs(np.mean(shares) - exact) < standard_error
    assert np.std(shares, ddof=1) < 0.3 * standard_error


def test_statistics_and_histogram():
    d = np.array([-3.0, -0.05, 0.05, 0.15, 2.0, 5.0])
    w = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 5.0])
    h = histogram(d, w, BANDS_MM)
    cfg = SETTINGS.analysis
    assert len(h.edges_mm) == round(2 * cfg.band_limit_mm / cfg.band_width_mm) + 1
    assert h.shares.sum() == pytest.approx(1.0)
    assert h.shares[0] == pytest.approx(0.1)  # -3 underflows
    assert h.shares[-1] == pytest.approx(0.6)  # 2.0 (upper edge) and 5.0 overflow
    assert h.shares[1 + 19] == pytest.approx(0.1)  # [-0.1, 0) holds -0.05
    s = deviation_stats(d, w)
    assert s.max_outside_mm == 5.0 and s.max_inside_mm == 3.0
    assert s.mean_mm == pytest.approx(np.sum(d * w) / w.sum())
    assert s.rms_mm == pytest.approx(np.sqrt(np.sum(d * d * w) / w.sum()))
    # |d| sorted 0.05, 0.05, 0.15, 2, 3, 5 (weight 5): the CDF reaches 0.5 at 3
    np.testing.assert_array_equal(weighted_percentiles(np.abs(d), w, [10, 50, 50.1, 99.9]), [0.05, 3.0, 5.0, 5.0])
    with pytest.raises(ValueError, match="whole number"):
        band_edges(0.3, 1.0)


def test_foot_points_across_a_face_boundary_are_refined_on_the_neighbour():
    """A C2 surface cut into two sewn faces measures like the uncut face: points whose
    nearest triangle lies on one face and foot point on the other are projected again."""
    from tests.test_analysis_continuity import two_patches

    split, whole = two_patches(1)
    settings = replace(TESSELLATION, deflection_mm=0.5, max_edge_mm=8.0)
    one = tessellate(whole, settings)
    two = tessellate(split, settings)
    rng = np.random.default_rng(4)
    # points near the cut (u = 1 is x = 20 mm), 1 mm off the surface on either side
    base = sample_surface(one.vertices, one.triangles, 20000, seed=4).points
    base = base[np.abs(base[:, 0] - 20.0) < 3.0]
    points = base + rng.uniform(-1.0, 1.0, (len(base), 1)) * np.array([0.0, 0.3, 1.0])
    ref = signed_distance_to_shape(points, one)
    got = signed_distance_to_shape(points, two)
    inner = ref.refined  # foot points inside the uncut face
    assert inner.mean() > 0.9
    assert got.refined[inner].all()
    np.testing.assert_allclose(got.distance_mm[inner], ref.distance_mm[inner], atol=1e-9)
