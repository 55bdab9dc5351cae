"""T-splines in OpenCascade: B-spline equality, Bezier faces, sewn shells."""
from __future__ import annotations

import numpy as np
import pytest

occ = pytest.importorskip("bonecad.occ.tspline")

from bonecad.occ.brep import is_valid, sew  # noqa: E402
from bonecad.splines.tspline import TSpline  # noqa: E402
from tests.test_tspline_core import size, t_tube, tube  # noqa: E402


def _values(surface, u, v) -> np.ndarray:
    out = []
    for a, b in zip(u, v):
        p = surface.Value(float(a), float(b))
        out.append((p.X(), p.Y(), p.Z()))
    return np.array(out)


@pytest.mark.parametrize("rational", [False, True])
def test_tensor_product_equals_occ_bspline_surface(rational):
    ts = tube(11, 6, seed=1, rational=rational)
    surf = occ.bspline_surface(ts)
    assert surf.IsUPeriodic() and not surf.IsVPeriodic()
    rng = np.random.default_rng(1)
    lo, hi = ts.mesh.s_range
    s = rng.uniform(lo, hi, 400)
    t = rng.uniform(*ts.mesh.t_range, 400)
    assert np.abs(_values(surf, s, t) - ts.evaluate(s, t).points).max() < 1e-9 * size(ts)


def test_open_tensor_product_equals_occ_bspline_surface():
    rng = np.random.default_rng(2)
    ts = TSpline.from_grid([0.0, 0.4, 1.1, 2.0], [0.0, 0.5, 1.0, 3.0], rng.normal(size=(6, 6, 3)),
                           rng.uniform(0.5, 2, (6, 6)))
    surf = occ.bspline_surface(ts)
    s, t = rng.uniform(0, 2, 300), rng.uniform(0, 3, 300)
    assert np.abs(_values(surf, s, t) - ts.evaluate(s, t).points).max() < 1e-9 * size(ts)


def test_t_junctions_have_no_single_bspline_surface():
    with pytest.raises(ValueError, match="not a tensor product"):
        occ.bspline_surface(t_tube(0))


@pytest.mark.parametrize("rational", [False, True])
def test_bezier_surfaces_match_the_t_spline(rational):
    ts = t_tube(3, rational=rational)
    ext = ts.extraction
    surfaces = occ.bezier_surfaces(ts)
    assert len(surfaces) == ext.n_elements
    rng = np.random.default_rng(3)
    for e in rng.choice(ext.n_elements, 25, replace=False):
        u, v = rng.uniform(0, 1, 8), rng.uniform(0, 1, 8)
        s = ext.s_bounds[e, 0] + u * np.diff(ext.s_bounds[e])
        t = ext.t_bounds[e, 0] + v * np.diff(ext.t_bounds[e])
        assert np.abs(_values(surfaces[e], u, v) - ts.evaluate(s, t).points).max() < 1e-9 * size(ts)


def test_sewn_shell_of_a_closed_tube_is_valid():
    from OCP.TopAbs import TopAbs_FACE
    from OCP.TopExp import TopExp_Explorer

    ts = t_tube(4, rational=True)
    shell = occ.to_shell(ts)
    assert is_valid(shell)
    n = 0
    explorer = TopExp_Explorer(shell, TopAbs_FACE)
    while explorer.More():
        n += 1
        explorer.Next()
    assert n == ts.extraction.n_elements


def _faces(shape) -> int:
    from OCP.TopAbs import TopAbs_FACE
    from OCP.TopExp import TopExp_Explorer

    n = 0
    explorer = TopExp_Explorer(shape, TopAbs_FACE)
    while explorer.More():
        n += 1
        explorer.Next()
    return n


@pytest.mark.parametrize("rational", [False, True])
def test_tensor_product_blocks_partition_the_elements_into_grids(rational):
    ts = t_tube(3, rational=rational)
    ext = ts.extraction
    blocks = occ.tensor_product_blocks(ts)
    elems = np.concatenate([b.ravel() for b in blocks])
    assert sorted(elems.tolist()) == list(range(ext.n_elements))
    assert len(blocks) < ext.n_elements // 4
    for b in blocks:
        assert (b >= 0).all()
        # a grid: equal t bounds along each row of elements, equal s widths along each column
        assert np.allclose(ext.t_bounds[b][:, :, 0], ext.t_bounds[b[:1]][:, :, 0])
        assert np.allclose(np.diff(ext.s_bounds[b], axis=-1), np.diff(ext.s_bounds[b[:, :1]], axis=-1))
        # consecutive elements touch, and the block does not close round s
        assert np.allclose(ext.t_bounds[b[:, :-1], 1], ext.t_bounds[b[:, 1:], 0])
        width = np.diff(ext.s_bounds[b[:, 0]], axis=1).sum()
        assert width < ts.mesh.s_period - 1e-12


@pytest.mark.parametrize("rational", [False, True])
def test_merged_surfaces_match_the_t_spline(rational):
    from OCP.Geom import Geom_BSplineSurface

    ts = t_tube(3, rational=rational)
    ext = ts.extraction
    rng = np.random.default_rng(4)
    merged = occ.merged_surfaces(ts)
    assert sum(b.size for _, b in merged) == ext.n_elements
    for surf, block in merged:
        u0, u1, v0, v1 = surf.Bounds()
        u, v = rng.uniform(u0, u1, 30), rng.uniform(v0, v1, 30)
        if block.size == 1:
            e = block[0, 0]
            s = ext.s_bounds[e, 0] + u * np.diff(ext.s_bounds[e])
            t = ext.t_bounds[e, 0] + v * np.diff(ext.t_bounds[e])
        else:
            assert isinstance(surf, Geom_BSplineSurface)
            # the T-spline is C2 inside a block: every interior knot is single again
            assert all(surf.UMultiplicity(k) == 1 for k in range(2, surf.NbUKnots()))
            assert all(surf.VMultiplicity(k) == 1 for k in range(2, surf.NbVKnots()))
            assert surf.NbUKnots() == block.shape[0] + 1 and surf.NbVKnots() == block.shape[1] + 1
            s, t = u, v
        assert np.abs(_values(surf, u, v) - ts.evaluate(s, t).points).max() < 1e-6


def test_tensor_product_tube_merges_into_two_faces():
    ts = tube(11, 6, seed=5)
    merged = occ.merged_surfaces(ts)
    # a block may not close round s: the widest block and the column left over
    assert len(merged) == 2 and sorted(b.shape[0] for _, b in merged) == [1, 10]


def test_merged_shell_is_valid_and_encloses_the_same_volume():
    from OCP.BRepGProp import BRepGProp
    from OCP.GProp import GProp_GProps

    ts = t_tube(4, rational=True)
    merged = sew([face for face, _ in occ.merged_faces(ts)], tolerance_mm=1e-6, closed=False)[0]
    assert is_valid(merged)
    assert _faces(merged) == len(occ.tensor_product_blocks(ts)) < ts.extraction.n_elements // 4
    areas = []
    for shell in (merged, occ.to_shell(ts)):
        props = GProp_GProps()
        BRepGProp.SurfaceProperties_s(shell, props, 1e-9)
        areas.append(props.Mass())
    assert abs(areas[0] - areas[1]) < 1e-7 * areas[1]


@pytest.mark.parametrize("rational", [False, True])
def test_merged_faces_bounded_by_one_edge_per_element_side(rational):
    from OCP.BRep import BRep_Tool
    from OCP.BRepGProp import BRepGProp
    from OCP.GProp import GProp_GProps

    from bonecad.occ.brep import edges

    ts = t_tube(4, rational=rational)
    natural = occ.merged_faces(ts)
    split = occ.merged_faces(ts, edge_per_element=True)
    assert len(split) == len(natural)
    for (face, block), (plain, _) in zip(split, natural):
        assert is_valid(face)
        assert BRep_Tool.Surface_s(face).Bounds() == BRep_Tool.Surface_s(plain).Bounds()
        sides = 4 if block.size == 1 else 2 * sum(block.shape)  # a Bezier face keeps its natural bounds
        assert len(edges(face)) == sides
        assert max(BRep_Tool.Tolerance_s(e) for e in edges(face)) <= 1e-7
    # the same shell, its edges cut at every element corner on a face's side
    areas = []
    for faces in (split, natural):
        shell = sew([face for face, _ in faces], tolerance_mm=1e-6, closed=False)[0]
        assert is_valid(shell)
        props = GProp_GProps()
        BRepGProp.SurfaceProperties_s(shell, props, 1e-9)
        areas.append(props.Mass())
    assert abs(areas[0] - areas[1]) < 1e-7 * areas[1]
