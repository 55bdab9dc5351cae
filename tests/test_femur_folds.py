"""Issue 45, no folds on a femur: the proximal contour curves neither cross themselves nor each other, and
the fitted T-spline has no folded element (docs/guides/femur-folds.md)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from bonecad.run.bones import bone_settings, named_bone
from bonecad.run.pipeline import frame_and_contours, load_input
from bonecad.settings import Settings
from bonecad.tspline_model.model import build_tspline_model
from tests.conftest import DATA

pytestmark = pytest.mark.slow


def _femur(name: str):
    path = DATA / "femur" / name
    if not path.exists():
        pytest.skip(f"{path} is absent")
    settings = Settings.load()
    settings = replace(settings, pipeline=replace(settings.pipeline, bone="femur"))
    bone = load_input(str(path), settings)
    settings = bone_settings(bone, settings)
    bone = named_bone(bone, settings)
    frame, contours, _ = frame_and_contours(bone, settings)
    return bone, frame, contours, settings


@pytest.fixture(scope="module")
def icl_femur():
    return _femur("ICL_MRI_femur_r.stl")


@pytest.fixture(scope="module")
def lhdl_femur():
    return _femur("LHDL_CT_femur_r.stl")


def _segments_cross(poly: np.ndarray) -> bool:
    """Whether two non-adjacent segments of a 2-D polyline (n, 2) cross."""
    a, b = poly[:-1], poly[1:]
    d = b - a

    def side(p, q, r):  # sign of the turn p -> q -> r for all pairs (i: p, q; j: r)
        return np.sign((q[:, None, 0] - p[:, None, 0]) * (r[None, :, 1] - p[:, None, 1])
                       - (q[:, None, 1] - p[:, None, 1]) * (r[None, :, 0] - p[:, None, 0]))

    crossing = (side(a, b, a) * side(a, b, b) < 0) & (side(a, b, a).T * side(a, b, b).T < 0)
    near = np.abs(np.subtract.outer(np.arange(len(d)), np.arange(len(d)))) < 2
    return bool((crossing & ~near).any())


def test_the_proximal_sections_neither_cross_themselves_nor_each_other(icl_femur):
    """Each proximal curve lies in its own half-plane about the local axis (so two curves meet at most on
    the axis, inside the apex hole) and its (radius, height) path in that half-plane does not cross itself."""
    u = np.linspace(-1.5, 1.5, 51)
    loop = np.column_stack([u**2 - 1, u * (u**2 - 1)])  # crosses itself at u = -1, 1
    assert _segments_cross(loop) and not _segments_cross(loop[:30])  # the check can fail
    _, _, contours, settings = icl_femur
    a, b = contours.local_axis_bone
    axis = (a - b) / np.linalg.norm(a - b)
    e1 = np.array([1.0, 0.0, 0.0]) - axis[0] * axis
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    for c in contours.proximal:
        p = c.curve(np.linspace(0.0, 1.0, 400)) - a
        theta = np.radians(c.angle)
        d = np.cos(theta) * e1 + np.sin(theta) * e2
        assert np.abs(p @ np.cross(axis, d)).max() < 1e-6, f"{c.name} leaves its half-plane"
        r = p @ d
        assert r.min() > settings.curves.apex_hole_radius_mm - 0.5, f"{c.name} reaches the axis"
        assert not _segments_cross(np.column_stack([r, p @ axis])), f"{c.name} crosses itself"


def test_the_lhdl_femurs_tspline_does_not_fold(lhdl_femur):
    """18 folded elements before the fit's data hook (tspline_model.model.MeshDataHook), 0 with it."""
    bone, frame, contours, settings = lhdl_femur
    model = build_tspline_model(bone, frame, contours, settings=settings.tspline,
                                apex_hole_radius_mm=settings.curves.apex_hole_radius_mm)
    assert model.fit.folded_elements == 0
