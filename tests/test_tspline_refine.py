"""Local refinement keeps the surface, grows the control net locally, stays
analysis-suitable; edge removal restores coarser meshes where the surface allows."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bonecad.splines.tspline import KnotSegment, check_suitability, insert_segments, refine_elements, remove_segments
from tests.test_tspline_core import random_params, size, t_tube, tube


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), picks=st.lists(st.floats(0.0, 1.0), min_size=1, max_size=6),
       rounds=st.integers(1, 3))
def test_refinement_keeps_the_surface_and_analysis_suitability(seed, picks, rounds):
    ts = tube(10, 7, seed=seed % 5, rational=bool(seed % 2))
    rng = np.random.default_rng(seed)
    s, t = random_params(ts, 2000, rng)
    before = ts.evaluate(s, t).points
    for _ in range(rounds):
        n_e = ts.extraction.n_elements
        result = refine_elements(ts, sorted({int(p * (n_e - 1)) for p in picks}))
        ts = result.tspline
        assert check_suitability(ts.mesh).suitable
        assert result.added >= 1
    assert np.abs(ts.evaluate(s, t).points - before).max() < 1e-9 * size(ts)
    assert np.abs(ts.blending_values(s[:300], t[:300]).sum(axis=1) - 1).max() < 1e-12


def test_refinement_matrix_maps_old_to_new_control_points():
    ts = t_tube(3, rational=True)
    r = refine_elements(ts, [10, 11, 40])
    pw_old = np.hstack([ts.control_points * ts.weights[:, None], ts.weights[:, None]])
    pw_new = np.hstack([r.tspline.control_points * r.tspline.weights[:, None], r.tspline.weights[:, None]])
    assert np.allclose(r.matrix @ pw_old, pw_new, atol=1e-12 * size(ts))
    assert np.all(r.matrix.getnnz(axis=1) > 0)  # every new control point comes from old ones
    assert np.allclose(r.matrix @ np.ones(ts.n_control), 1.0)  # partition of unity is kept


def test_control_points_grow_only_locally():
    ts = tube(40, 30, seed=4)
    n_s, n_t = 40, 30 + 2
    ext = ts.extraction
    e = int(np.flatnonzero((ext.index_bounds[:, 0] == 20) & (ext.index_bounds[:, 2] == 15))[0])
    r = refine_elements(ts, [e])
    new = r.tspline
    # a tensor product would add a whole row and column
    assert 0 < r.added < (n_s + n_t) / 4
    assert r.requested_vertices <= r.added
    old = {tuple(p) for p in np.round(ts.anchor_params, 12)}
    added = np.array([p for p in np.round(new.anchor_params, 12) if tuple(p) not in old])
    assert len(added) == r.added
    s0, s1 = ext.s_bounds[e]
    t0, t1 = ext.t_bounds[e]
    ds = 3 * np.diff(ts.mesh.s_lines).max()
    dt = 3 * np.diff(ts.mesh.t_lines).max()
    assert np.all((added[:, 0] > s0 - ds) & (added[:, 0] < s1 + ds))
    assert np.all((added[:, 1] > t0 - dt) & (added[:, 1] < t1 + dt))
    # the untouched control points are bit-identical (the two rows at each
    # clamped end share their parameters, so compare the rows between them)
    keep = {tuple(p): c for p, c in zip(np.round(new.anchor_params, 12), new.control_points)}
    t_end = ts.mesh.t_range
    far = (np.abs(ts.anchor_params[:, 1] - 0.5 * (t0 + t1)) > 4 * dt) & ~np.isin(ts.anchor_params[:, 1], t_end)
    for p, c in zip(np.round(ts.anchor_params[far], 12), ts.control_points[far]):
        assert np.array_equal(keep[tuple(p)], c)


def test_segment_insertion_adds_the_vertices_suitability_needs():
    ts = tube(16, 12, seed=5)
    rng = np.random.default_rng(5)
    s, t = random_params(ts, 1000, rng)
    before = ts.evaluate(s, t).points
    lines = ts.mesh.t_lines[3:-3]
    # a short s-segment and a t-segment stopping just before it: their
    # extensions meet, so the closure must extend one of them
    k = int(np.searchsorted(ts.mesh.s_lines, 0.55)) - 1
    segs = [
        KnotSegment("s", 0.55, lines[4], lines[5]),
        KnotSegment("t", 0.5 * (lines[6] + lines[7]), ts.mesh.s_lines[k - 2], ts.mesh.s_lines[k]),
    ]
    assert not check_suitability(insert_segments_unclosed(ts, segs)).suitable
    r = insert_segments(ts, segs)
    assert check_suitability(r.tspline.mesh).suitable
    assert r.added > r.requested_vertices  # suitability/consistency needed extra control points
    assert np.abs(r.tspline.evaluate(s, t).points - before).max() < 1e-9 * size(ts)


def insert_segments_unclosed(ts, segs):
    """The mesh with the segments inserted and nothing else (to show closure is needed)."""
    from bonecad.splines.tspline.refine import _Edges, _snap, _snap_s

    mesh = ts.mesh
    for seg in segs:
        mesh = mesh.with_line(seg.axis, seg.value, 1e-12)[0]
    ks = [mesh.with_line(seg.axis, seg.value, 1e-12)[1] for seg in segs]  # indices in the final grid
    edges = _Edges(mesh)
    for seg, k in zip(segs, ks):
        if seg.axis == "s":
            edges.add_s_line(k, *_snap(mesh.t_lines, seg.lo, seg.hi, 1e-12))
        else:
            edges.add_t_line(k, *_snap_s(mesh, seg.lo, seg.hi, 1e-12))
    return edges.snapshot()


def test_every_requested_segment_lies_on_its_own_line_whatever_the_order():
    """Lines inserted later below an earlier one shift its index: the segment must still land on it."""
    ts = tube(12, 8, seed=3)
    ext = ts.extraction
    e = int(np.flatnonzero((ext.index_bounds[:, 0] == 6) & (ext.index_bounds[:, 2] == 5))[0])
    (s0, s1), (t0, t1) = ext.s_bounds[e], ext.t_bounds[e]
    # the higher s-line first, then one below it, then t-lines the same way
    segs = [KnotSegment("s", s0 + 0.75 * (s1 - s0), t0, t1), KnotSegment("s", s0 + 0.25 * (s1 - s0), t0, t1),
            KnotSegment("t", t0 + 0.75 * (t1 - t0), s0, s1), KnotSegment("t", t0 + 0.25 * (t1 - t0), s0, s1)]
    mesh = insert_segments(ts, segs).tspline.mesh
    for seg in segs:
        k = int(np.flatnonzero(np.isclose(mesh.s_lines if seg.axis == "s" else mesh.t_lines, seg.value))[0])
        if seg.axis == "s":  # the s-line's edges between t0 and t1
            span = (mesh.t_lines >= t0 - 1e-12) & (mesh.t_lines <= t1 + 1e-12)
            assert mesh.t_edges[k, np.flatnonzero(span)[:-1]].all()
        else:
            span = (mesh.s_lines >= s0 - 1e-12) & (mesh.s_lines <= s1 + 1e-12)
            assert mesh.s_edges[k, np.flatnonzero(span)[:-1]].all()


def test_refinement_across_the_seam_and_segment_errors():
    ts = tube(12, 8, seed=6)
    lo, hi = ts.mesh.s_range
    lines = ts.mesh.t_lines[3:-3]
    r = insert_segments(ts, [KnotSegment("t", 0.5 * (lines[2] + lines[3]), hi - 0.2, hi + 0.2)])
    rng = np.random.default_rng(6)
    s, t = random_params(ts, 1000, rng)
    assert np.abs(r.tspline.evaluate(s, t).points - ts.evaluate(s, t).points).max() < 1e-9 * size(ts)
    with pytest.raises(ValueError, match="outside the parameter range"):
        insert_segments(ts, [KnotSegment("t", lines[-1] + 5.0, 0.0, 0.5)])
    with pytest.raises(ValueError, match="lo < hi"):
        insert_segments(ts, [KnotSegment("s", 0.5, 2.0, 1.0)])
    with pytest.raises(ValueError, match="axis"):
        insert_segments(ts, [KnotSegment("u", 0.5, 0.0, 1.0)])


def test_removal_restores_the_coarse_mesh_exactly():
    ts = tube(16, 12, seed=7)
    lines = ts.mesh.t_lines[3:-3]
    seg = KnotSegment("s", 0.9, lines[2], lines[9])
    fine = insert_segments(ts, [seg]).tspline
    assert fine.n_control > ts.n_control
    back = remove_segments(fine, [seg])
    assert back.tspline.n_control == ts.n_control
    assert back.max_deviation_mm < 1e-9 * size(ts)
    assert np.allclose(back.tspline.control_points, ts.control_points, atol=1e-9 * size(ts))


def test_removal_where_the_surface_does_not_allow_it_reports_the_deviation():
    ts = tube(16, 12, seed=8)
    lines = ts.mesh.t_lines[3:-3]
    seg = KnotSegment("s", 0.9, lines[2], lines[9])
    fine = insert_segments(ts, [seg]).tspline
    cp = fine.control_points.copy()
    near = np.argmin(np.linalg.norm(fine.anchor_params - [0.9, lines[5]], axis=1))
    cp[near] += 2.0  # a bump the coarse mesh cannot carry
    bumped = type(fine)(fine.mesh, cp, fine.weights)
    out = remove_segments(bumped, [seg])
    assert 0.01 < out.max_deviation_mm < 2.0


def test_removal_refuses_meshes_that_lose_suitability():
    ts = tube(16, 12, seed=9)
    lines = ts.mesh.t_lines[3:-3]
    s_lines = ts.mesh.s_lines
    i = 8
    with pytest.raises(ValueError, match="not analysis-suitable"):
        remove_segments(
            ts,
            [
                KnotSegment("s", s_lines[i], lines[4], lines[6]),
                KnotSegment("t", lines[5], s_lines[i - 1], s_lines[i + 1]),
            ],
        )
    with pytest.raises(ValueError, match="not a knot line"):
        remove_segments(ts, [KnotSegment("s", 0.123456, lines[1], lines[3])])


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000), picks=st.lists(st.floats(0.0, 1.0), min_size=2, max_size=10),
       rounds=st.integers(1, 3))
def test_one_way_splits_keep_the_surface_and_add_fewer_control_points(seed, picks, rounds):
    ts = four = tube(10, 7, seed=seed % 5, rational=bool(seed % 2))
    rng = np.random.default_rng(seed)
    s, t = random_params(ts, 2000, rng)
    before = ts.evaluate(s, t).points
    for _ in range(rounds):
        n_e = ts.extraction.n_elements
        e = sorted({int(p * (n_e - 1)) for p in picks})
        axes = np.zeros((len(e), 2), dtype=bool)
        axes[np.arange(len(e)), rng.integers(0, 2, len(e))] = True  # each element halved one way only
        ts = refine_elements(ts, e, axes).tspline
        four = refine_elements(four, sorted({int(p * (four.extraction.n_elements - 1)) for p in picks})).tspline
        assert check_suitability(ts.mesh).suitable
    assert np.abs(ts.evaluate(s, t).points - before).max() < 1e-9 * size(ts)
    assert ts.n_control < four.n_control


def test_one_way_split_of_one_element_adds_one_line_segment():
    ts = tube(40, 30, seed=4)
    ext = ts.extraction
    e = int(np.flatnonzero((ext.index_bounds[:, 0] == 20) & (ext.index_bounds[:, 2] == 15))[0])
    for axes, count in (([[True, False]], 2), ([[False, True]], 2)):
        r = refine_elements(ts, [e], np.array(axes))
        assert r.added == count  # the two ends of the new segment, nothing else on a tensor grid
    with pytest.raises(ValueError, match="axes"):
        refine_elements(ts, [e], np.ones((2, 2), dtype=bool))


def test_neighbours_split_across_each_other_need_two_extra_control_points():
    # an element halved in s next to one halved in t: the t-segment's face
    # extension meets the s-segment's edge extensions; extending the s-segment's
    # two ends one face each clears both (the t-segment would need two faces
    # and still touch), so 4 requested + 2 control points, exact and suitable
    ts = tube(40, 30, seed=4)
    ib = ts.extraction.index_bounds
    e = [int(np.flatnonzero((ib[:, 0] == i) & (ib[:, 2] == 15))[0]) for i in (20, 21)]
    r = refine_elements(ts, e, np.array([[True, False], [False, True]]))
    assert (r.requested_vertices, r.added) == (4, 6)
    assert check_suitability(r.tspline.mesh).suitable
    s, t = random_params(ts, 1000, np.random.default_rng(3))
    assert np.abs(r.tspline.evaluate(s, t).points - ts.evaluate(s, t).points).max() < 1e-9 * size(ts)


def test_crossing_a_point_on_a_perpendicular_edge_adds_one_side_only():
    from bonecad.splines.tspline.refine import _Edges

    ts = tube(16, 12, seed=5)
    mesh, k, _ = ts.mesh.with_line("s", 0.5 * (ts.mesh.s_lines[6] + ts.mesh.s_lines[7]), 1e-12)
    edges = _Edges(mesh)
    edges.cross_at(k, 8, "s")  # t-line 8 is complete: one face up or down suffices
    assert edges.t_e[k].sum() == 1 and (edges.t_e[k, 7] or edges.t_e[k, 8])
    mesh2, j, _ = mesh.with_line("t", 0.5 * (mesh.t_lines[8] + mesh.t_lines[9]), 1e-12)
    edges = _Edges(mesh2)
    edges.cross_at(k, j, "s")  # inside a face: the segment must cross it, from edge to edge
    assert edges.t_e[k].sum() == 2 and edges.t_e[k, j - 1] and edges.t_e[k, j]
