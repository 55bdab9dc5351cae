"""NURBS baseline: interpolation invariants, the sewn solid on the phantom (both apex fills, a mirrored
frame), seams, deviation against the mesh, STEP/IGES round trips, one real mesh."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bonecad.splines.curve import BSplineCurve
from bonecad.contours.curves import contour_curves
from bonecad.export.registry import export
from bonecad.nurbs_model import FACE_NAMES, build_nurbs
from bonecad.splines.surface import BSplineSurface
from bonecad.occ import brep
from bonecad.occ import surfaces as occ
from bonecad.splines.knots import periodic_knots
from bonecad.splines.surface import interpolate_clamped, interpolate_periodic

from .conftest import real_mesh_params
from tests.defaults import SETTINGS, TESSELLATION, BANDS_MM
from dataclasses import replace
from bonecad.occ.tessellate import tessellate



def mesh_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    t = vertices[faces]
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


# --- numpy interpolation and the OCP boundary ---------------------------------------------------


def test_periodic_interpolation_reproduces_values_and_stays_seamless(rng):
    values = rng.normal(size=(28, 5, 3))
    poles = interpolate_periodic(values)
    curve = BSplineCurve(poles[:, 2], periodic_knots(28), 3, True)
    np.testing.assert_allclose(curve(np.arange(28) / 28), values[:, 2], atol=1e-12)
    # no double knot at the seam: the curve is C2 across u = 0
    for nu in (0, 1, 2):
        np.testing.assert_allclose(curve(np.array([1.0 - 1e-9]), nu), curve(np.array([0.0]), nu), rtol=1e-6, atol=1e-6)


def test_periodic_interpolation_rejects_parameters_out_of_order():
    with pytest.raises(Exception, match="once round in order"):
        interpolate_periodic(np.zeros((4, 3)), np.array([0.0, 0.5, 0.25, 0.75]))


def test_clamped_interpolation_reproduces_values(rng):
    params = np.concatenate([[0.0], np.sort(rng.random(6)), [1.0]])
    values = rng.normal(size=(8, 3))
    poles, knots = interpolate_clamped(values, params)
    np.testing.assert_allclose(BSplineCurve(poles, knots)(params), values, atol=1e-10)


def test_surface_matches_opencascade_and_reversal_keeps_points(rng):
    poles = rng.normal(size=(7, 6, 3))
    knots_v = np.array([0, 0, 0, 0, 0.3, 0.6, 1, 1, 1, 1.0])
    surface = BSplineSurface(poles, periodic_knots(7), knots_v, periodic_u=True, region="test")
    geom = occ.to_geom_surface(surface)
    u, v = rng.random(50), rng.random(50)
    ours = surface.evaluate(u, v).points
    theirs = np.array([[p.X(), p.Y(), p.Z()] for p in (geom.Value(float(a), float(b)) for a, b in zip(u, v))])
    np.testing.assert_allclose(ours, theirs, atol=1e-10)
    np.testing.assert_allclose(surface.reversed_v().evaluate(u, 1.0 - v).points, ours, atol=1e-10)
    assert geom.IsUPeriodic() and not geom.IsVPeriodic()
    assert all(geom.UMultiplicity(i) == 1 for i in range(1, geom.NbUKnots() + 1))  # no double knot at the seam


# --- the phantom ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def contours(phantom_contours):
    return phantom_contours


@pytest.fixture(scope="module")
def ring_model(contours):
    return build_nurbs(contours, settings=replace(SETTINGS.nurbs, apex_fill="ring"))


@pytest.fixture(scope="module")
def patch_model(contours):
    return build_nurbs(contours, settings=replace(SETTINGS.nurbs, apex_fill="patch"))


def check_solid(model, mesh_vol: float) -> None:
    assert brep.is_valid(model.shape)
    assert brep.free_edge_count(model.shape) == 0
    assert [name for name, _ in model.face_names] == list(FACE_NAMES)
    assert model.faces == 5
    assert model.volume_mm3 > 0
    assert abs(model.volume_mm3 / mesh_vol - 1.0) < 0.01


@pytest.mark.parametrize("fill", ["ring", "patch"])
def test_phantom_gives_one_valid_closed_solid(fill, ring_model, patch_model, phantom):
    model = ring_model if fill == "ring" else patch_model
    check_solid(model, mesh_volume(phantom.vertices, phantom.faces))
    # volume of the B-rep against the exact integral of the mesh: the phantom is smooth, so tight
    assert abs(model.volume_mm3 / mesh_volume(phantom.vertices, phantom.faces) - 1.0) < 0.002
    assert model.control_points == sum(s.poles.shape[0] * s.poles.shape[1] for s in model.surfaces)
    assert [s.region for s in model.surfaces] == list(FACE_NAMES)


def test_own_faces_point_outward(ring_model):
    # every face bonecad parametrises itself keeps its natural orientation in the solid
    assert not any(brep.face_is_reversed(face) for _, face in ring_model.face_names)
    assert not any(s.reversed for s in ring_model.surfaces)


def test_shaft_meets_the_ends_exactly(ring_model):
    assert ring_model.boundary_gap_mm == (0.0, 0.0)
    distal, shaft, proximal = (occ.to_geom_surface(ring_model.surface(n)) for n in ("distal", "shaft", "proximal"))
    u = np.linspace(0.0, 1.0, 97)
    for a, va, b, vb in ((distal, 1.0, shaft, 0.0), (shaft, 1.0, proximal, 0.0)):
        gap = max(a.Value(float(t), va).Distance(b.Value(float(t), vb)) for t in u)
        assert gap < 1e-9
    # the iso-curves that replace the shaft's own end sections stay close to them (sub-mm)
    assert max(ring_model.boundary_shift_mm) < 0.5


def test_compatible_curves_keep_the_contour_tolerances(ring_model):
    for report in ring_model.refits:
        assert report.max_deviation_mm <= getattr(SETTINGS.curves, f"{report.region}_tolerance_mm"), report


def test_patch_caps_are_tangent_to_their_neighbours(patch_model):
    tol = SETTINGS.nurbs.sewing_tolerance_mm
    assert set(patch_model.patch_errors) == {"distal_apex_cap", "proximal_apex_cap"}
    for errors in patch_model.patch_errors.values():
        assert errors["g0_mm"] <= tol
        assert errors["g1_rad"] < 0.15  # about 9 degrees; the ring cone breaks by far more
    caps = [s for s in patch_model.surfaces if s.region.endswith("apex_cap")]
    assert all(s.degree_u >= 3 and not s.periodic_u for s in caps)


def test_deviation_from_the_phantom_mesh(ring_model, phantom):
    from bonecad.analysis.deviation import shape_deviation

    # 0.1 mm chords are enough: every sample is refined on the exact surface (checked below)
    tess = tessellate(ring_model.shape, replace(TESSELLATION, deflection_mm=0.1, max_edge_mm=2.0))
    result = shape_deviation(phantom.vertices, phantom.faces, tess, edges_mm=BANDS_MM, sample_points=20000)
    for direction in (result.mesh_to_cad, result.cad_to_mesh):
        dev, w = np.abs(direction.deviation_mm), direction.weights
        assert direction.refined.mean() > 0.99
        assert w[dev <= 1.0].sum() / w.sum() > 0.999
        assert w[dev <= 0.25].sum() / w.sum() > 0.97
        assert dev.max() < 1.5


def test_step_and_iges_round_trip(ring_model, tmp_path):
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.IGESControl import IGESControl_Reader
    from OCP.STEPControl import STEPControl_Reader
    from OCP.TopAbs import TopAbs_SOLID
    from OCP.TopExp import TopExp_Explorer

    paths = export("nurbs", ring_model, tmp_path)
    text = paths["step"].read_text()
    for name in FACE_NAMES:
        assert f"ADVANCED_FACE('{name}'" in text
    assert "MANIFOLD_SOLID_BREP('nurbs'" in text

    reader = STEPControl_Reader()
    assert reader.ReadFile(str(paths["step"])) == IFSelect_RetDone
    reader.TransferRoots()
    shape = reader.OneShape()
    explorer, solids = TopExp_Explorer(shape, TopAbs_SOLID), []
    while explorer.More():
        solids.append(explorer.Current())
        explorer.Next()
    assert len(solids) == 1
    assert brep.is_valid(solids[0]) and brep.free_edge_count(solids[0]) == 0
    assert len(brep.faces(solids[0])) == 5
    assert brep.volume_mm3(solids[0]) == pytest.approx(ring_model.volume_mm3, rel=1e-5)

    iges = IGESControl_Reader()
    assert iges.ReadFile(str(paths["iges"])) == IFSelect_RetDone
    iges.TransferRoots()
    assert len(brep.faces(iges.OneShape())) == 5
    assert "distal_apex_cap" in paths["iges"].read_text().replace("\n", "")


def test_left_tibia_gives_an_outward_solid(contours, phantom, ring_model):
    # The same bone mirrored in scanner space: bone coordinates (and curves) stay the same, the
    # frame becomes a mirror. The solid must still be valid with outward faces (positive volume).
    mirror = np.diag([-1.0, 1.0, 1.0])
    frame = dataclasses.replace(contours.frame, axes=contours.frame.axes @ mirror,
                                origin=contours.frame.origin @ mirror)
    assert frame.mirrored
    left = build_nurbs(dataclasses.replace(contours, frame=frame), settings=replace(SETTINGS.nurbs, apex_fill="ring"))
    check_solid(left, mesh_volume(phantom.vertices @ mirror, phantom.faces[:, ::-1]))
    assert left.volume_mm3 == pytest.approx(ring_model.volume_mm3, rel=1e-6)
    # the mirror image of each surface point of the right model lies on the left model
    right, mirrored = ring_model.surface("shaft"), left.surface("shaft")
    np.testing.assert_allclose(mirrored.evaluate(0.3, 1.0 - 0.4).points, right.evaluate(0.3, 0.4).points @ mirror,
                               atol=1e-9)


def test_unknown_apex_fill_is_refused(contours):
    """From a file or a flag it is bad input (exit 2, see test_settings); from code, a ValueError."""
    with pytest.raises(ValueError, match="apex_fill must be one of"):
        build_nurbs(contours, settings=replace(SETTINGS.nurbs, apex_fill="plug"))


# --- one real mesh (all five in benchmarks/bench_nurbs.py) ---------------------------------------


def _one_real_mesh():
    """The smallest real mesh (coarse MRI, 15 k triangles), or the skip reason when the data is absent."""
    params = real_mesh_params()
    return [p for p in params if p.id == "ICL_MRI_tibia_r"] or params[:1]


@pytest.mark.parametrize("path", _one_real_mesh())
def test_real_mesh_gives_a_valid_closed_solid(path):
    import bonecad

    bone = bonecad.load_bone(path)
    frame = bonecad.anatomical_frame(bone)
    model = build_nurbs(contour_curves(bone, frame, settings=SETTINGS.curves), settings=SETTINGS.nurbs)
    check_solid(model, mesh_volume(bone.vertices, bone.faces))


def test_model_pickles_with_its_solid_and_face_names(ring_model):
    """A model handed between processes (bonecad.run.executor) keeps its exact solid and names."""
    import json
    import pickle

    back = pickle.loads(pickle.dumps(ring_model))
    assert [n for n, _ in back.face_names] == [n for n, _ in ring_model.face_names]
    assert brep.is_valid(back.shape) and brep.free_edge_count(back.shape) == 0
    assert brep.volume_mm3(back.shape) == pytest.approx(brep.volume_mm3(ring_model.shape), rel=1e-12)
    for (name, a), (_, b) in zip(ring_model.face_names, back.face_names):
        assert brep.area_mm2(a) == pytest.approx(brep.area_mm2(b), rel=1e-12), name
    assert json.dumps(back.summary()) == json.dumps(ring_model.summary())  # NaN-safe
