"""Issue 45: the verdict reads both directions, and a fold (a sheet of the surface turned back on itself)
fails the model however close the mesh lies to it."""
from __future__ import annotations

import numpy as np
import pytest

from bonecad.analysis.deviation import shape_deviation
from bonecad.analysis.folds import surface_folds
from bonecad.analysis.model import ModelReport
from bonecad.export.report import MET, NOT_MET, Tolerances, verdict
from bonecad.splines.folds import largest_turn_deg
from bonecad.splines.surface import BSplineSurface
from tests.defaults import BANDS_MM
from tests.test_analysis_report import sphere, wavy_mesh  # noqa: F401 (the module's sphere fixture)


def _clamped(n: int) -> np.ndarray:
    return np.concatenate([[0.0] * 3, np.linspace(0.0, 1.0, n - 2), [1.0] * 3])


def _sheet(fold_mm: float) -> BSplineSurface:
    """A 40 x 40 mm bicubic sheet, 9 x 9 poles; one column of poles pushed back along x by ``fold_mm``
    (beyond its neighbour's place when ``fold_mm`` exceeds the 5 mm pole spacing: the sheet folds)."""
    x, y = np.meshgrid(np.linspace(0, 40, 9), np.linspace(0, 40, 9), indexing="ij")
    poles = np.stack([x, y, 0.02 * (x - 20) ** 2], axis=-1)
    poles[4, :, 0] -= fold_mm
    return BSplineSurface(poles, _clamped(9), _clamped(9))


def test_a_folded_sheet_is_found_and_a_smooth_one_is_not():
    smooth = surface_folds(_sheet(0.0))
    assert smooth.elements == 36 and smooth.reversed_elements == 0
    bent = surface_folds(_sheet(3.0))  # steeper, but not turned back
    assert bent.reversed_elements == 0
    folded = surface_folds(_sheet(12.0), "shaft")
    assert folded.reversed_elements > 0
    assert all(name == "shaft" and turn > 90 for name, *_, turn in folded.where)


def test_degenerate_samples_carry_no_normal():
    """A collapsed pole row (S_u = 0 along one edge) is no fold."""
    du = np.zeros((1, 4, 4, 3))
    dv = np.zeros((1, 4, 4, 3))
    du[..., 0], dv[..., 1] = 1.0, 1.0
    du[:, 0] = 0.0  # the pole row
    assert largest_turn_deg(du, dv)[0] == pytest.approx(0.0)


def test_verdict_fails_when_the_cad_strays_from_the_mesh_while_the_mesh_hugs_the_cad(sphere):  # noqa: F811
    """The sphere model against a wavy sphere mesh with its top cap cut off (z > 8 mm): every mesh point
    lies near the model (mesh -> CAD holds), but the model's cap lies up to 6 mm from the mesh (CAD -> mesh):
    the verdict must say not met, naming that direction."""
    shape, tess = sphere
    v, f = wavy_mesh(tess, 0.05)
    keep = v[f].mean(axis=1)[:, 2] < 8.0
    dev = shape_deviation(v, f[keep], tess, edges_mm=BANDS_MM, sample_points=20000)
    near = dev.mesh_to_cad.stats
    worst_near = max(near.max_outside_mm, near.max_inside_mm)
    far = dev.cad_to_mesh.stats
    assert max(far.max_outside_mm, far.max_inside_mm) > 5.0
    tol = Tolerances(share=0.95, within_mm=0.25, max_deviation_mm=worst_near + 0.05, rms_mm=near.rms_mm + 0.05)
    result = verdict(ModelReport("tspline", {}, dev), tol)
    assert result["verdict"] == NOT_MET
    assert "CAD to mesh: largest deviation" in result["reason"]
    assert not any(c["check"].startswith("mesh to CAD") and not c["met"] for c in result["checks"])
    whole = shape_deviation(v, f, tess, edges_mm=BANDS_MM, sample_points=20000)
    assert verdict(ModelReport("tspline", {}, whole), tol)["verdict"] == MET
