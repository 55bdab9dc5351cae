"""The T-spline model of a voxel staircase whose smooth bone is known (the real
LHDL CT tibia, turned into the binary 1 mm mask surface an MRI segmentation
like JIA's gives): the fit lands on the bone, not on the steps.

The 99 % within 0.25 mm bar cannot be met against such data: the bone itself
is that close to only about 80 % of its staircase. What the fit can and must
do is recover the bone (figures: benchmarks/bench_staircase.py)."""
from __future__ import annotations

import numpy as np
import pytest

from .conftest import TIBIA_DIR
from tests.defaults import SETTINGS, TESSELLATION, BANDS_MM
from dataclasses import replace
from bonecad.occ.tessellate import tessellate


SMOOTH_TIBIA = TIBIA_DIR / "LHDL_CT_tibia_no_fib_r.stl"
pytestmark = pytest.mark.skipif(not SMOOTH_TIBIA.is_file(), reason=f"real mesh {SMOOTH_TIBIA} is absent")


@pytest.fixture(scope="module")
def truth():
    import bonecad

    return bonecad.load_bone(SMOOTH_TIBIA)


@pytest.fixture(scope="module")
def staircase(truth):
    from bonecad.imaging.compare import staircase_mesh
    from bonecad.mesh.intake import prepare_bone

    vertices, faces = staircase_mesh(truth.vertices, truth.faces, 1.0)
    return prepare_bone(vertices, faces, source="LHDL staircase", settings=SETTINGS.mesh, plausible=SETTINGS.units)


def test_staircase_is_the_binary_mask_surface(truth, staircase):
    from bonecad.analysis.deviation import sample_surface
    from bonecad.analysis.statistics import share_within
    from bonecad.imaging.compare import distance_to_surface
    from bonecad.splines.tspline.fit import voxel_step_mm

    assert voxel_step_mm(staircase.vertices) == pytest.approx(1.0)
    assert staircase.bodies[0].volume_mm3 == pytest.approx(truth.bodies[0].volume_mm3, rel=0.01)
    samples = sample_surface(staircase.vertices, staircase.faces, 50_000, seed=0)
    d = distance_to_surface(truth.to_trimesh(), samples.points)
    # the bone itself misses the 99 % bar against its staircase
    assert 0.7 < share_within(d, samples.weights, 0.25) < 0.85
    assert d.max() < 0.6  # but it lies within about half a voxel of every step


def test_fit_to_the_staircase_recovers_the_bone(truth, staircase):
    import bonecad
    from bonecad.analysis.deviation import shape_deviation
    from bonecad.contours.curves import contour_curves
    from bonecad.tspline_model import build_tspline_model

    frame = bonecad.anatomical_frame(staircase)
    model = build_tspline_model(staircase, frame, contour_curves(staircase, frame, settings=SETTINGS.curves),
                                settings=SETTINGS.tspline, apex_hole_radius_mm=SETTINGS.curves.apex_hole_radius_mm)
    assert "up to the data's noise" in model.fit.stopped, model.fit.stopped
    assert model.summary()["staircase_voxel_mm"] == pytest.approx(1.0)
    # Chasing the steps to the 20000-point budget took 19484 points and left the
    # surface farther from the bone (92 % within 0.25 mm): the noise stop needs 1228.
    assert model.control_points < 3000
    tess = tessellate(model.shape, replace(TESSELLATION, coverage_tolerance=0.01))
    dev = shape_deviation(truth.vertices, truth.faces, tess, edges_mm=BANDS_MM, sample_points=50_000)
    bone_to_model = dev.mesh_to_cad
    assert bone_to_model.share_within(0.25) >= 0.96
    assert np.abs(bone_to_model.deviation_mm).max() <= 1.0
    assert bone_to_model.stats.rms_mm <= 0.11
