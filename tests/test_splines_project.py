"""Point projection (bonecad.splines.project) on analytic curves and surfaces."""
from __future__ import annotations

import numpy as np

from bonecad.splines.curve import BSplineCurve
from bonecad.splines.surface import BSplineSurface, SurfaceSet
from bonecad.splines.project import project_faces, project_to_curve


def quarter_cylinder(radius: float = 10.0, height: float = 20.0) -> BSplineSurface:
    """The exact rational quarter cylinder x^2 + y^2 = r^2, x, y >= 0, 0 <= z <= height (u: angle, v: z)."""
    corner = np.array([[radius, 0.0], [radius, radius], [0.0, radius]])
    poles = np.stack([np.column_stack([corner, np.full(3, z)]) for z in (0.0, height)], axis=1)  # (3, 2, 3)
    weights = np.array([[1.0, 1.0], [np.sqrt(0.5)] * 2, [1.0, 1.0]])
    return BSplineSurface(poles, np.array([0, 0, 0, 1, 1, 1.0]), np.array([0, 0, 1, 1.0]), 2, 1, weights=weights)


def test_projection_onto_a_cylinder_finds_the_radial_foot_point():
    rng = np.random.default_rng(3)
    angle = rng.uniform(0.05, 0.5 * np.pi - 0.05, 500)
    z = rng.uniform(1.0, 19.0, 500)
    r = 10.0 + rng.uniform(-3.0, 3.0, 500)
    points = np.column_stack([r * np.cos(angle), r * np.sin(angle), z])
    proj = project_faces(SurfaceSet([quarter_cylinder()]), np.zeros(500, dtype=np.int64), points,
                         np.full((500, 2), 0.5))
    expected = np.column_stack([10.0 * np.cos(angle), 10.0 * np.sin(angle), z])
    np.testing.assert_allclose(proj.foot, expected, atol=1e-6)
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", proj.normal, points - proj.foot)), np.abs(r - 10.0),
                               atol=1e-6)
    assert proj.residual_mm.max() < 1e-6 and not proj.clamped.any()


def test_projection_clamps_beyond_the_face():
    point = np.array([[-5.0, 5.0, 10.0]])  # angle 135 degrees: the foot point lies past the face's end u = 1
    proj = project_faces(SurfaceSet([quarter_cylinder()]), np.zeros(1, dtype=np.int64), point, np.array([[0.5, 0.5]]))
    assert proj.clamped[0] and proj.uv[0, 0] == 1.0


def test_curve_projection_is_orthogonal_on_a_parabola():
    parabola = BSplineCurve(np.array([[-1.0, 1.0, 0.0], [0.0, -1.0, 0.0], [1.0, 1.0, 0.0]]),
                            np.array([0, 0, 0, 1, 1, 1.0]), degree=2)  # y = x^2, x = 2u - 1
    rng = np.random.default_rng(4)
    x = rng.uniform(-0.8, 0.8, 200)
    normal = np.column_stack([-2 * x, np.ones_like(x), np.zeros_like(x)])
    points = np.column_stack([x, x**2, np.zeros_like(x)]) + 0.05 * normal / np.linalg.norm(normal, axis=1)[:, None]
    u = project_to_curve(parabola, points, iterations=8)  # from the nearest dense sample
    np.testing.assert_allclose(2 * u - 1, x, atol=1e-9)
