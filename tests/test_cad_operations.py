"""What a CAD user does first with bonecad's models, on the STEP files as written and re-read:
offset, thick solid, osteotomy, drill, section (OpenCascade); FreeCAD opens them; a plate's footprint."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from bonecad.occ.exchange import read_named_step
from bonecad.occ.brep import is_valid
from bonecad.occ.operations import run_cad_operations, shells, solids, thicken
from bonecad.run.cli import main

from .defaults import SETTINGS
from .freecad import freecad_check, freecad_command

OPERATIONS = ["offset", "thick_solid", "osteotomy", "drill", "section"]


def _assert_all_pass(path):
    solid, named = read_named_step(path)
    ops = run_cad_operations(solid)
    assert [op.name for op in ops] == OPERATIONS
    failed = {op.name: op.problem for op in ops if not op.passed}
    assert not failed, f"{path.name}: {failed}"
    return named, {op.name: op for op in ops}


@pytest.mark.parametrize("model", ["nurbs", "tspline"])
def test_phantom_models_pass_the_five_operations(phantom_run, model):
    named, ops = _assert_all_pass(phantom_run / f"{model}.step")
    assert {"distal_apex_cap", "proximal_apex_cap"} <= {name for name, _ in named}
    assert ops["osteotomy"].figures["relative_imbalance"] <= 1e-4
    assert ops["section"].figures["closed_wires"] == ops["section"].figures["wires"] >= 1


def test_report_says_which_joins_were_built_and_measures_them(phantom_run):
    nurbs = json.loads((phantom_run / "report.json").read_text())["models"]["nurbs"]
    assert nurbs["info"]["joins"] == "G1"
    counts = nurbs["continuity"]["summary"]["class_counts"]
    assert counts["C0"] == counts["gap"] == 0 and counts["G1"] == 4  # tangent, not curvature-continuous


def test_the_whole_tube_as_one_exact_bspline_face(phantom_run, tmp_path, rng):
    """The "tube" layout's face: the T-spline's tensor-product form on its global knot lines."""
    from bonecad.occ.brep import write_named_step
    from bonecad.occ.tspline import bspline_face
    from bonecad.splines.tspline import from_dict
    from bonecad.splines.tspline.tensor import tensor_product_form
    from OCP.BRep import BRep_Tool

    tube = from_dict(json.loads((phantom_run / "tspline.json").read_text())["tube"])
    face = bspline_face(tensor_product_form(tube))
    surface = BRep_Tool.Surface_s(face)
    (s0, s1), (t0, t1) = tube.mesh.s_range, tube.mesh.t_range
    s, t = rng.uniform(s0, s1, 300), rng.uniform(t0, t1, 300)
    got = np.array([surface.Value(float(a), float(b)).Coord() for a, b in zip(s, t)])
    assert np.abs(got - tube.evaluate(s, t).points).max() < 1e-6
    path = write_named_step(face, tmp_path / "tube.step", "tube", [("tube", face)])
    assert path.stat().st_size < (phantom_run / "tspline.step").stat().st_size


def test_c0_joins_are_the_papers_and_do_not_offset(phantom_contours, tmp_path):
    """The paper's C0 joins stay an option; OpenCascade refuses to offset them (why G1 is the default)."""
    from bonecad.nurbs_model.model import build_nurbs
    from bonecad.occ.brep import write_named_step

    model = build_nurbs(phantom_contours, settings=replace(SETTINGS.nurbs, joins="C0"))
    assert model.summary()["joins"] == "C0"
    path = write_named_step(model.shape, tmp_path / "nurbs.step", "nurbs", list(model.face_names))
    ops = {op.name: op for op in run_cad_operations(read_named_step(path)[0])}
    assert not ops["offset"].passed and "MixedConnectivity" in ops["offset"].problem
    assert ops["osteotomy"].passed and ops["drill"].passed and ops["section"].passed


def test_real_tibia_models_pass_the_five_operations(real_tibia_run):
    for model in ("nurbs", "tspline"):
        _assert_all_pass(real_tibia_run / f"{model}.step")
    assert (real_tibia_run / "tspline.step").stat().st_size <= 2_000_000  # lean STEP (panels): 1.26 MB measured


def test_the_thick_solid_wall_follows_the_bones_face_order(real_tibia_run):
    """The wall's offset face i lies beside the bone's face i (CI once saw BRepCheck call ICL's wall an
    "EnclosedRegion": BRepOffset orders the offset faces by memory address, and the check's verdict followed)."""
    from OCP.BRepGProp import BRepGProp
    from OCP.GProp import GProp_GProps
    from OCP.TopoDS import TopoDS_Iterator

    def centroids(shell):
        found, iterator = [], TopoDS_Iterator(shell)
        while iterator.More():
            props = GProp_GProps()
            BRepGProp.SurfaceProperties_s(iterator.Value(), props)
            found.append(props.CentreOfMass().Coord())
            iterator.Next()
        return np.array(found)

    solid, faces = read_named_step(real_tibia_run / "tspline.step")
    (wall,) = solids(thicken(shells(solid)[0], -1.0))
    bone, offset = (centroids(s) for s in shells(wall))
    assert len(bone) == len(offset) == len(faces)  # (ICL: 15; the panel plan follows the T-mesh)
    apart = np.linalg.norm(offset[:, None] - bone[None], axis=2)
    assert list(apart.argmin(axis=1)) == list(range(len(bone)))
    assert is_valid(wall)


@pytest.mark.skipif(freecad_command() is None, reason="FreeCAD is not installed (no freecadcmd on PATH; Debian: "
                    "apt-get install freecad)")
@pytest.mark.parametrize("model", ["nurbs", "tspline"])
def test_freecad_opens_each_model_as_one_valid_closed_solid(phantom_run, model):
    from bonecad.occ.brep import volume_mm3

    verdict = freecad_check(phantom_run / f"{model}.step")
    assert verdict.one_valid_closed_solid, verdict.summary()
    solid, _ = read_named_step(phantom_run / f"{model}.step")
    assert verdict.volumes_mm3[0] == pytest.approx(volume_mm3(solid), rel=1e-3)


def test_patch_is_exact_untrimmed_and_thickens_into_a_plate_blank(phantom_run, tmp_path, capsys):
    from OCP.BRep import BRep_Tool
    from OCP.BRepTools import BRepTools
    from OCP.Geom import Geom_BSplineSurface

    from bonecad.occ.brep import area_mm2, faces, volume_mm3
    from bonecad.occ.operations import offset_shape
    from bonecad.splines.tspline import from_dict

    out = tmp_path / "patch"
    assert main(["patch", str(phantom_run), "--region", "anteromedial_distal_tibia", "--out", str(out)]) == 0
    assert "plate blank valid" in capsys.readouterr().out
    doc = json.loads((out / "patch.json").read_text())
    assert doc["deviation_from_tspline_mm"] < 1e-6
    assert doc["deviation_from_mesh"]["rms_mm"] < 0.25
    assert doc["plate_blank"]["valid"] and doc["plate_blank"]["solids"] == 1
    # the STEP face: one untrimmed B-spline face on the T-spline (scanner coordinates)
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.STEPControl import STEPControl_Reader

    reader = STEPControl_Reader()
    assert reader.ReadFile(str(out / "patch.step")) == IFSelect_RetDone
    reader.TransferRoots()
    (face,) = faces(reader.OneShape())
    surface = BRep_Tool.Surface_s(face)
    assert isinstance(surface, Geom_BSplineSurface)
    assert np.allclose(BRepTools.UVBounds_s(face), surface.Bounds(), atol=1e-9)  # natural bounds: untrimmed
    tube = from_dict(json.loads((phantom_run / "tspline.json").read_text())["tube"])
    s0, s1, t0, t1 = surface.Bounds()  # the patch keeps the tube's parameters: u = s, v = t
    assert [s0, s1] == pytest.approx(doc["parameters"]["s"], abs=1e-6)
    u, v = np.linspace(s0, s1, 7), np.linspace(t0, t1, 7)
    uu, vv = (a.ravel() for a in np.meshgrid(u, v))
    got = np.array([surface.Value(float(a), float(b)).Coord() for a, b in zip(uu, vv)])
    s_lo = tube.mesh.s_range[0]
    want = tube.evaluate(s_lo + np.mod(uu - s_lo, tube.mesh.s_period), vv).points
    assert np.abs(got - want).max() < 1e-6
    # the plate: offset 1 mm off the bone, thickened 3 mm into one valid solid
    gap = offset_shape(face, 1.0)
    assert is_valid(gap) and area_mm2(gap) == pytest.approx(area_mm2(face), rel=0.1)
    (blank,) = solids(thicken(face, 3.0))
    assert is_valid(blank)
    assert volume_mm3(blank) == pytest.approx(3.0 * area_mm2(face), rel=0.1)
