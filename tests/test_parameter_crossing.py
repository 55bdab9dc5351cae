"""Issue 45: before each solve the T-spline fit leaves out the points whose parameters cross their
neighbours' (a mesh triangle whose (s, t) image turns over) and puts them back at parameters interpolated
from the points about them, and samples inside every triangle whose image leaves a part of the domain bare:
a least-squares fit folds on crossing parameters and where no datum holds it."""
from __future__ import annotations

import numpy as np

from bonecad.splines.tspline import TMesh, TSpline
from bonecad.splines.tspline.fit import solve_control_points
from bonecad.tspline_model.model import MeshDataHook
from bonecad.tspline_model.skinning import turned_over_triangles

N = 12  # grid points around (s, period N) and along (t)
T0 = 20.0  # t of the first row: clear of the apex ring (t = 0), where triangles are not judged


def _cylinder() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points of a cylinder (radius N / 2 pi, so s and t are both mm), their (s, t) and triangles whose
    normals point outwards."""
    s, t = np.meshgrid(np.arange(N, dtype=float), np.arange(N, dtype=float), indexing="ij")
    s, t = s.ravel(), t.ravel() + T0
    r = N / (2 * np.pi)
    points = np.column_stack([r * np.cos(s / r), r * np.sin(s / r), t - T0])
    idx = np.arange(N * N).reshape(N, N)
    quads = [(idx[i, j], idx[(i + 1) % N, j], idx[(i + 1) % N, j + 1], idx[i, j + 1])
             for i in range(N) for j in range(N - 1)]
    triangles = np.array([q for a, b, c, d in quads for q in ((a, b, c), (a, c, d))])
    return points, s, t, triangles


def _surface(points: np.ndarray, s: np.ndarray, t: np.ndarray) -> TSpline:
    """The cylinder fitted on a coarse T-mesh."""
    mesh = TMesh.grid(np.arange(0.0, N, 3.0), np.arange(T0, T0 + 19.0, 3.0), s_period=float(N))
    blank = TSpline(mesh, np.zeros((len(mesh.anchors), 3)), np.ones(len(mesh.anchors)))
    return solve_control_points(blank, s, t, points, fairness=1e-4)


def _hook(points, triangles) -> MeshDataHook:
    """A hook that has seen a fold over the whole cylinder (it acts only about folds)."""
    hook = MeshDataHook(points, np.ones(len(points)), triangles, float(N), 400.0)
    hook.fold_boxes.append((N / 2, N, 0.0, 400.0))
    return hook


def test_a_fit_that_never_folded_is_left_alone():
    points, s, t, triangles = _cylinder()
    moved = t.copy()
    moved[3 * N + 5] = T0 + 6.6
    hook = MeshDataHook(points, np.ones(len(points)), triangles, float(N), 400.0)
    left_out, extra = hook(_surface(points, s, t), s, moved)
    assert not left_out.any() and extra is None and not hook.fold_boxes


def test_a_point_pushed_past_its_neighbour_is_left_out_and_put_back_between_its_neighbours():
    points, s, t, triangles = _cylinder()
    hook = _hook(points, triangles)
    ts = _surface(points, s, t)
    left_out, extra = hook(ts, s, t)
    assert not turned_over_triangles(s, t, triangles, float(N)).any()  # across the periodic seam too
    assert not left_out.any() and extra is None
    k = 3 * N + 5  # s = 3, t = 5, pushed beyond the t = 6 row
    moved = t.copy()
    moved[k] = T0 + 6.6
    assert turned_over_triangles(s, moved, triangles, float(N)).any()
    left_out, extra = hook(ts, s, moved)
    assert left_out[k] and 3 < left_out.sum() < 30  # the point, its triangles' corners and their neighbours
    assert extra is not None
    p, es, et, _ = extra
    mine = np.flatnonzero(np.all(p == points[k], axis=1))
    assert len(mine) == 1
    assert np.isclose(es[mine[0]], 3.0, atol=1e-9) and np.isclose(et[mine[0]], T0 + 5.0, atol=0.05)


def test_a_triangle_stretched_over_the_domain_is_sampled_inside():
    points, s, t, triangles = _cylinder()
    hook = _hook(points, triangles)
    stretched = t.copy()
    stretched[t >= T0 + 6] += 6.0  # a 6 mm gap in t between the rows t = 5 and t = 6: no point maps into it
    left_out, extra = hook(_surface(points, s, t), s, stretched)
    assert not left_out.any() and extra is not None
    p, es, et, w = extra
    gap = et - T0
    assert ((gap >= 5.0) & (gap <= 12.0)).all()  # in the gap (its rows' edges included)
    assert np.sum((gap > 5.5) & (gap < 11.5)) >= 2 * N  # inside it, from every triangle across it
    assert np.allclose(p[:, 2], 5 + (gap - 5) / 7)  # on the facet, at the same barycentric parameters
    assert (w > 0).all()
