"""Continuity and zebra analysis on shapes whose continuity is known by construction."""
from __future__ import annotations

import numpy as np
import pytest

from bonecad.analysis.continuity import knot_continuity, seam_continuity
from bonecad.render.figures import VIEWS, render_tessellation_normals, screen_axes, zebra_image, zebra_png
from bonecad.occ.tessellate import tessellate
from tests.defaults import TESSELLATION, CONTINUITY
from dataclasses import replace


def _bspline(poles, ku, mu, kv, mv, p=3, q=3):
    from OCP.Geom import Geom_BSplineSurface
    from OCP.gp import gp_Pnt
    from OCP.TColgp import TColgp_Array2OfPnt
    from OCP.TColStd import TColStd_Array1OfInteger, TColStd_Array1OfReal

    nu, nv = poles.shape[:2]
    arr = TColgp_Array2OfPnt(1, nu, 1, nv)
    for i in range(nu):
        for j in range(nv):
            arr.SetValue(i + 1, j + 1, gp_Pnt(*map(float, poles[i, j])))

    def seq(values, cls):
        a = cls(1, len(values))
        for i, v in enumerate(values):
            a.SetValue(i + 1, v)
        return a

    return Geom_BSplineSurface(
        arr, seq(ku, TColStd_Array1OfReal), seq(kv, TColStd_Array1OfReal),
        seq(mu, TColStd_Array1OfInteger), seq(mv, TColStd_Array1OfInteger), p, q,
    )


def two_patches(interior_multiplicity: int):
    """One bicubic surface with a knot of the given multiplicity at u = 1, split there into two sewn faces.

    Multiplicity 1: C2 join, 2: C1 (curvature jumps), 3: C0 (tangent jumps).
    """
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace, BRepBuilderAPI_Sewing

    nu = 4 + interior_multiplicity
    x, y = np.meshgrid(np.linspace(0, 40, nu), np.linspace(0, 30, 4), indexing="ij")
    z = 5 * np.sin(x / 9.0) + 3 * np.cos(y / 11.0) + 0.002 * x * y
    surf = _bspline(np.stack([x, y, z], axis=-1), [0.0, 1.0, 2.0], [4, interior_multiplicity, 4], [0.0, 1.0], [4, 4])
    sew = BRepBuilderAPI_Sewing(1e-6)
    for lo, hi in ((0.0, 1.0), (1.0, 2.0)):
        part = surf.Copy()
        part.Segment(lo, hi, 0.0, 1.0)
        sew.Add(BRepBuilderAPI_MakeFace(part, 1e-7).Face())
    sew.Perform()
    whole = BRepBuilderAPI_MakeFace(surf, 1e-7).Face()
    return sew.SewedShape(), whole


def test_box_fails_g1_on_every_edge_at_90_degrees():
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeBox

    result = seam_continuity(BRepPrimAPI_MakeBox(10.0, 20.0, 30.0).Shape(), tolerances=CONTINUITY)
    assert len(result.classes) == 12
    assert set(result.classes) == {"C0"}
    np.testing.assert_allclose(result.angle_deg, 90.0, atol=1e-9)
    assert result.gap_mm.max() < 1e-9
    assert result.summary()["class_counts"]["C0"] == 12
    np.testing.assert_allclose(sorted(result.length_mm), sorted([10.0] * 4 + [20.0] * 4 + [30.0] * 4))


def test_c1_join_passes_g1_and_fails_g2():
    shape, whole = two_patches(2)
    result = seam_continuity(shape, tolerances=CONTINUITY)
    assert list(result.classes) == ["G1"]
    assert result.angle_deg.max() < 1e-4
    assert result.curvature_jump.max() > 0.2
    knots = knot_continuity(whole)[0]
    assert knots.kind == "bspline"
    assert knots.min_continuity.tolist() == [1, 99]
    assert knots.low_knots[0] == [(1.0, 2, 1)]


def test_c2_join_passes_g2():
    shape, whole = two_patches(1)
    result = seam_continuity(shape, tolerances=CONTINUITY)
    assert list(result.classes) == ["G2"]
    assert result.curvature_jump.max() < 1e-8
    assert knot_continuity(whole)[0].min_continuity.tolist() == [2, 99]


def test_c0_join_fails_g1_and_thresholds_move_the_class():
    shape, _ = two_patches(3)
    result = seam_continuity(shape, tolerances=CONTINUITY)
    assert list(result.classes) == ["C0"]
    angle = result.angle_deg.max()
    assert angle > 1.0
    loose = seam_continuity(shape, tolerances=replace(CONTINUITY, angle_deg=angle + 1, curvature_jump=10.0))
    assert list(loose.classes) == ["G2"]


def test_periodic_seam_is_not_a_shared_edge_and_knots_report_it():
    from OCP.BRepBuilderAPI import BRepBuilderAPI_NurbsConvert
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeCylinder

    cyl = BRepBuilderAPI_NurbsConvert(BRepPrimAPI_MakeCylinder(5.0, 20.0).Shape(), True).Shape()
    result = seam_continuity(cyl, tolerances=CONTINUITY)
    assert len(result.classes) == 2 and set(result.classes) == {"C0"}  # the two rims
    kinds = {k.kind for k in knot_continuity(cyl)}
    assert kinds == {"bspline"}


def _zebra_rows(shape):
    """Zebra image of the posterior view, and the image column of the seam x = 20 mm."""
    frame = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]).T  # looking down -z onto the patches
    tess = tessellate(shape, TESSELLATION)
    raster = render_tessellation_normals(tess, frame, ("posterior",), height_px=240)[0]
    img = zebra_image(raster, stripes=30)[..., 0] > 0.5
    left, right = raster.extent_mm[:2]
    axes = screen_axes(frame, "posterior")
    seam_col = int((20.0 * axes[0, 0] - left) / (right - left) * img.shape[1])
    return img, raster.mask, seam_col


def _stripe_jump(img, mask, col):
    """Share of rows where stripe colour differs across the seam column, minus that elsewhere."""
    rows = mask[:, col - 3] & mask[:, col + 3]
    across = np.mean(img[rows, col - 2] != img[rows, col + 2])
    ref_col = col // 2
    rows_ref = mask[:, ref_col - 3] & mask[:, ref_col + 3]
    baseline = np.mean(img[rows_ref, ref_col - 2] != img[rows_ref, ref_col + 2])
    return across - baseline


def test_zebra_stripes_break_at_a_tangent_break_only():
    c0, _ = two_patches(3)
    c2, _ = two_patches(1)
    jump_c0 = _stripe_jump(*_zebra_rows(c0))
    jump_c2 = _stripe_jump(*_zebra_rows(c2))
    assert jump_c0 > 0.05
    assert abs(jump_c2) < 0.03


def test_zebra_png_four_views(tmp_path):
    """Four panels from the four sides; a zebra figure has no colour, so it is written greyscale."""
    from PIL import Image

    shape, _ = two_patches(2)
    path = zebra_png(tmp_path / "zebra.png", tessellate(shape, TESSELLATION), np.eye(3), height_px=200)
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    assert VIEWS == ("anterior", "posterior", "medial", "lateral")
    image = Image.open(path)
    assert image.mode == "L" and image.size[1] >= 200


def test_zebra_stripes_fade_to_grey_where_denser_than_the_pixels():
    """A pixel spanning many stripes shows their mean (mid grey), not one of them (aliasing)."""
    from bonecad.render.figures import Raster

    h, w = 4, 64
    angle = np.linspace(0.0, 0.5 * np.pi, w)  # normals tilting across the row: the phase grows along it
    normal = np.zeros((h, w, 3))
    normal[..., 1], normal[..., 2] = np.sin(angle), np.cos(angle)
    raster = Raster(np.ones((h, w), bool), np.zeros((h, w)), np.zeros((h, w, 1)), normal, (0.0, 64.0, 0.0, 4.0))
    coarse = zebra_image(raster, stripes=4)[..., 0] / (0.55 + 0.45 * normal[..., 2])
    fine = zebra_image(raster, stripes=400)[..., 0] / (0.55 + 0.45 * normal[..., 2])
    assert coarse.min() < 0.1 and coarse.max() > 0.9  # resolved: dark and light bands
    assert np.all(np.abs(fine[:, 1:-1] - (0.08 + 0.87 / 2)) < 0.1)  # ~6 stripes per pixel: their mean


def test_frame_must_be_a_rotation():
    with pytest.raises(ValueError, match="orthonormal"):
        screen_axes(np.diag([1.0, 2.0, 1.0]), "anterior")
    with pytest.raises(ValueError, match="view must be"):
        screen_axes(np.eye(3), "superior")


@pytest.mark.parametrize("kind", ["rational sphere", "bicubic with a double knot"])
def test_batched_second_derivatives_match_opencascade(kind):
    """SurfaceSet.evaluate to order 2 (the batched seam evaluation) against BRepLProp_SLProps, point by point."""
    from OCP.BRepAdaptor import BRepAdaptor_Surface
    from OCP.BRepBuilderAPI import BRepBuilderAPI_NurbsConvert
    from OCP.BRepLProp import BRepLProp_SLProps
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeSphere

    from bonecad.splines.surface import SurfaceSet
    from bonecad.occ.brep import faces
    from bonecad.occ.read_faces import face_spline_surface

    if kind == "rational sphere":
        face = faces(BRepBuilderAPI_NurbsConvert(BRepPrimAPI_MakeSphere(40.0).Shape(), True).Shape())[0]
    else:
        face = two_patches(2)[1]
    surface, native = face_spline_surface(face)
    assert native
    rng = np.random.default_rng(0)
    u0, u1, v0, v1 = surface.bounds
    u = rng.uniform(u0, u1, 40)
    v = rng.uniform(v0 + 0.02 * (v1 - v0), v1 - 0.02 * (v1 - v0), 40)  # away from the sphere's poles
    sample = SurfaceSet([surface]).evaluate(np.zeros(40, dtype=np.int64), u, v, order=2)
    got = sample.points, sample.du, sample.dv, sample.duu, sample.dvv, sample.duv
    props = BRepLProp_SLProps(BRepAdaptor_Surface(face), 2, 1e-9)
    for i in range(40):
        props.SetParameters(float(u[i]), float(v[i]))
        for k, vec in enumerate((props.Value(), props.D1U(), props.D1V(), props.D2U(), props.D2V(), props.DUV())):
            want = np.array([vec.X(), vec.Y(), vec.Z()])
            np.testing.assert_allclose(got[k][i], want, atol=1e-9 * (1 + np.abs(want).max()))
