"""T-splines in OpenCascade: B-spline equality, Bezier faces, sewn shells."""
from __future__ import annotations

import numpy as np
import pytest

occ = pytest.importorskip("bonecad.tspline.occ")

from bonecad.errors import InputError  # noqa: E402
from bonecad.tspline import TSpline  # noqa: E402
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
    ts = TSpline.from_grid([0.0, 0.4, 1.1, 2.0], [0.0, 0.5, 1.0, 3.0], rng.normal(size=(6, 6, 3)), rng.uniform(0.5, 2, (6, 6)))
    surf = occ.bspline_surface(ts)
    s, t = rng.uniform(0, 2, 300), rng.uniform(0, 3, 300)
    assert np.abs(_values(surf, s, t) - ts.evaluate(s, t).points).max() < 1e-9 * size(ts)


def test_t_junctions_have_no_single_bspline_surface():
    with pytest.raises(InputError, match="not a tensor product"):
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
    assert occ.is_valid(shell)
    n = 0
    explorer = TopExp_Explorer(shell, TopAbs_FACE)
    while explorer.More():
        n += 1
        explorer.Next()
    assert n == ts.extraction.n_elements
