"""CI regression of deviation histograms: the models of reference meshes against stored goldens.

Update on purpose with ``BONECAD_UPDATE_GOLDENS=1 python -m pytest tests/test_goldens.py``.
"""
from __future__ import annotations

import functools

import pytest

import bonecad
from tests.goldens import GoldenMismatch, assert_fairness_matches, assert_histogram_matches
from bonecad.analysis.model import region_labels
from bonecad.analysis.deviation import shape_deviation
from bonecad.contours.curves import contour_curves

from .conftest import TIBIA_DIR
from tests.defaults import BANDS_MM, SETTINGS, TESSELLATION
from bonecad.occ.tessellate import tessellate


REFERENCES = ["LHDL_CT_tibia_no_fib_r", "TLEM2_CT_tibia_r"]
SAMPLES = 100_000
TOLERANCE = 0.01  # one percentage point of surface per 0.1 mm band


@functools.cache
def _reference(stem: str):
    path = TIBIA_DIR / f"{stem}.stl"
    if not path.exists():
        pytest.skip(f"reference mesh {path} is absent")
    bone = bonecad.load_bone(path)
    frame = bonecad.anatomical_frame(bone)
    return bone, frame, contour_curves(bone, frame, settings=SETTINGS.curves)


def _nurbs_deviation(stem: str, perturb_mm: float = 0.0):
    from bonecad.nurbs_model.model import build_nurbs

    bone, frame, contours = _reference(stem)
    shape = build_nurbs(contours, settings=SETTINGS.nurbs).shape
    if perturb_mm:
        shape = _moved(shape, perturb_mm)
    return shape_deviation(bone.vertices, bone.faces, tessellate(shape, TESSELLATION), regions=region_labels(frame),
                           edges_mm=BANDS_MM, sample_points=SAMPLES)


def _moved(shape, distance_mm: float):
    """The model moved sideways by ``distance_mm`` (a deliberately perturbed model)."""
    from OCP.BRepBuilderAPI import BRepBuilderAPI_Transform
    from OCP.gp import gp_Trsf, gp_Vec

    move = gp_Trsf()
    move.SetTranslation(gp_Vec(distance_mm, 0.0, 0.0))
    return BRepBuilderAPI_Transform(shape, move, True).Shape()


@pytest.mark.parametrize("stem", REFERENCES)
def test_nurbs_histogram_matches_golden(stem):
    deviation = _nurbs_deviation(stem)
    assert_histogram_matches(deviation.mesh_to_cad.histogram, f"nurbs_{stem}", tolerance=TOLERANCE)
    if stem == REFERENCES[0]:
        from bonecad.nurbs_model.model import build_nurbs

        _, frame, contours = _reference(stem)
        _assert_fairness(build_nurbs(contours, settings=SETTINGS.nurbs).shape, frame, f"fairness_nurbs_{stem}")
    for region, histogram in deviation.mesh_to_cad.region_histograms.items():
        assert_histogram_matches(histogram, f"nurbs_{stem}_{region}", tolerance=TOLERANCE)
    # the other direction, where a fold or a stray sheet of the model shows (issue 45)
    assert_histogram_matches(deviation.cad_to_mesh.histogram, f"nurbs_{stem}_cad_to_mesh", tolerance=TOLERANCE)


def test_tspline_histogram_matches_golden(tmp_path):
    from bonecad.tspline_model.model import build_tspline_model
    from tests.tsm_checks import assert_model_cage, assert_open_patch

    stem = REFERENCES[0]
    bone, frame, contours = _reference(stem)
    model = build_tspline_model(bone, frame, contours, settings=SETTINGS.tspline,
                                apex_hole_radius_mm=SETTINGS.curves.apex_hole_radius_mm)
    shape = model.shape
    # the same real tibia's model as .tsm: the closed Fusion cage, and an open patch in Rhino's convention
    assert_model_cage(model, tmp_path)
    assert_open_patch(model.tspline)
    deviation = shape_deviation(bone.vertices, bone.faces, tessellate(shape, TESSELLATION),
                                regions=region_labels(frame), edges_mm=BANDS_MM, sample_points=SAMPLES)
    assert_histogram_matches(deviation.mesh_to_cad.histogram, f"tspline_{stem}", tolerance=TOLERANCE)
    assert_histogram_matches(deviation.cad_to_mesh.histogram, f"tspline_{stem}_cad_to_mesh", tolerance=TOLERANCE)
    _assert_fairness(shape, frame, f"fairness_tspline_{stem}")


def _assert_fairness(shape, frame, name: str) -> None:
    """The model's fairness figure, overall and per region, within 5 % of its golden (a change of the fit's
    refinement moves it by tens of per cent; ripple of 0.02 mm at 3 mm by several times)."""
    from bonecad.analysis.model import model_fairness

    fairness = model_fairness(shape, frame, SETTINGS.analysis)
    assert_fairness_matches({"overall": fairness.curvature_variation, **fairness.regions,
                             "median": fairness.typical}, name)


def test_perturbed_model_is_caught():
    deviation = _nurbs_deviation(REFERENCES[0], perturb_mm=0.15)
    with pytest.raises(GoldenMismatch):
        assert_histogram_matches(deviation.mesh_to_cad.histogram, f"nurbs_{REFERENCES[0]}", tolerance=TOLERANCE,
                                 update=False)
