"""``bonecad plate``: the plate solid, its fit and its screws, each checked independently of the plan: the solid
re-read from STEP (OpenCascade, FreeCAD), the fit and penetration from plate.stl against the bone mesh (trimesh),
the screw lengths from trimesh's own ray cast, the clearances from sampled segments, the joints from frame.json."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from bonecad.run.cli import main

from .conftest import DATA
from .freecad import freecad_check, freecad_command

#: CT meshes: ICL's MRI meshes are rough (noise level 0.114 mm), their T-spline stops at the noise, and a plate
#: seated on it puts only 90-94 % of its underside within gap + 0.5 mm (a known miss, docs/guides/plate.md)
CT_TIBIA = DATA / "tibia" / "LHDL_CT_tibia_no_fib_r.stl"
CT_FEMUR = DATA / "femur" / "LHDL_CT_femur_r.stl"


def _plate(source: Path, out: Path, *flags: str) -> dict:
    assert main(["plate", str(source), "--out", str(out), *flags, "-q"]) == 0
    return json.loads((out / "plate.json").read_text())


def _bone_mesh(path: Path) -> trimesh.Trimesh:
    """The bone of a mesh file: its largest body (the tibia of a tibia + fibula file), read by trimesh."""
    bodies = trimesh.load(path, force="mesh").split(only_watertight=False)
    return max(bodies, key=lambda b: abs(b.volume))


def _screws(out: Path) -> list[dict]:
    with (out / "screws.csv").open() as f:
        return list(csv.DictReader(f))


def _xyz(row: dict, name: str) -> np.ndarray:
    return np.array([float(row[f"{name}_{a}"]) for a in "xyz"])


def _segment_gap(a0, a1, b0, b1) -> float:
    """Distance between two segments, by 0.05 mm samples (independent of the plan's closed form)."""
    sa = a0 + np.linspace(0, 1, int(np.linalg.norm(a1 - a0) / 0.05) + 2)[:, None] * (a1 - a0)
    sb = b0 + np.linspace(0, 1, int(np.linalg.norm(b1 - b0) / 0.05) + 2)[:, None] * (b1 - b0)
    from scipy.spatial import cKDTree

    return float(cKDTree(sb).query(sa)[0].min())


def check_plate(out: Path, run: Path, mesh_path: Path, *, joints_clear: bool) -> dict:
    """Every check of the issue on one plate folder; returns figures for the caller."""
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.STEPControl import STEPControl_Reader

    from bonecad.occ.brep import edges, is_valid, volume_mm3
    from bonecad.occ.operations import solids

    doc = json.loads((out / "plate.json").read_text())
    design = doc["design"]
    gap, d = design["gap_mm"], design["screw_diameter_mm"]
    # one valid closed solid, re-read from STEP
    reader = STEPControl_Reader()
    assert reader.ReadFile(str(out / "plate.step")) == IFSelect_RetDone
    reader.TransferRoots()
    (solid,) = solids(reader.OneShape())
    assert is_valid(solid)
    assert volume_mm3(solid, 1e-8) == pytest.approx(doc["plate"]["volume_mm3"], rel=1e-4)
    # the centre line and one axis per screw as STEP curves
    reader = STEPControl_Reader()
    assert reader.ReadFile(str(out / "plate_curves.step")) == IFSelect_RetDone
    reader.TransferRoots()
    assert len(edges(reader.OneShape())) == 1 + len(doc["screws"])
    # the plate's triangulation against the bone mesh: closed, nowhere inside the bone beyond 0.1 mm
    plate = trimesh.load(out / "plate.stl", force="mesh")
    bone = _bone_mesh(mesh_path)
    assert plate.is_watertight
    assert plate.volume == pytest.approx(doc["plate"]["volume_mm3"], rel=0.01)
    query = trimesh.proximity.ProximityQuery(bone)
    depth = query.signed_distance(plate.vertices)  # > 0 inside the bone
    assert depth.max() <= 0.1, f"the plate is up to {depth.max():.3f} mm inside the bone"
    # the underside (faces facing along the nearest screw, into the bone): 99 % of its area within gap + 0.5 mm
    rows = _screws(out)
    heads = np.array([_xyz(r, "head") for r in rows])
    dirs = np.array([_xyz(r, "dir") for r in rows])
    centres = plate.triangles_center
    nearest = np.argmin(np.linalg.norm(centres[:, None] - heads[None], axis=2), axis=1)
    under = np.einsum("ij,ij->i", plate.face_normals, dirs[nearest]) > 0.7
    distance = np.abs(query.signed_distance(centres[under]))
    area = plate.area_faces[under]
    share = float(area[distance <= gap + 0.5].sum() / area.sum())
    assert share >= 0.99, f"{100 * share:.2f} % of the underside within gap + 0.5 mm"
    # screws: the length to the far cortex by trimesh's ray cast, stock, clearance, joints
    frame = json.loads((run / "frame.json").read_text())
    up, origin = np.array(frame["bone_frame"]["proximal"]), np.array(frame["bone_frame"]["origin"])
    low, high = ((np.array(frame["apices"][e]) - origin) @ up for e in ("distal", "proximal"))
    margin = design["joint_margin_mm"]
    intersector = trimesh.ray.ray_triangle.RayMeshIntersector(bone)
    tips = []
    for row, head, direction in zip(rows, heads, dirs):
        hits, _, _ = intersector.intersects_location([head], [direction])
        far = np.max((hits - head) @ direction)
        length, stock = float(row["length_mm"]), float(row["stock_mm"])
        assert length == pytest.approx(far, abs=0.5), f"screw {row['hole']}: {length} mm, ray cast {far:.2f} mm"
        assert length <= stock < length + design["stock_step_mm"] + 1e-6
        assert stock <= design["max_screw_length_mm"]
        exit_height = (_xyz(row, "exit") - origin) @ up
        into_joint = not low + margin <= exit_height <= high - margin
        assert into_joint == ("articular end" in row["warnings"]), row
        if joints_clear:
            assert not into_joint, f"screw {row['hole']} exits {exit_height - low:.1f} mm above the distal apex"
        tips.append(head + stock * direction)
    for i in range(len(rows)):
        for j in range(i + 1, len(rows)):
            gap_ij = _segment_gap(heads[i], tips[i], heads[j], tips[j]) - d
            assert gap_ij >= d - 0.05 or "less than a screw diameter" in rows[i]["warnings"]
            if joints_clear:
                assert gap_ij >= d - 0.05, f"screws {i + 1} and {j + 1} pass {gap_ij:.2f} mm apart"
    return {"share": share, "depth": float(depth.max())}


@pytest.fixture(scope="module")
def phantom_plate(phantom_run, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("plate") / "phantom"
    _plate(phantom_run, out, "--region", "anteromedial_distal_tibia")
    return out


def test_phantom_plate_is_one_valid_solid_that_fits_and_its_screws_match_a_ray_cast(phantom_run, phantom_plate):
    check_plate(phantom_plate, phantom_run, phantom_run.parent / "phantom.stl", joints_clear=True)
    doc = json.loads((phantom_plate / "plate.json").read_text())
    assert doc["plate"]["valid"] and doc["plate"]["solids"] == 1
    assert doc["plate"]["mass_g"] == pytest.approx(doc["plate"]["volume_mm3"] / 1000 * 4.43, rel=1e-3)
    assert doc["fit"]["share_within_gap_plus_mm"]["0.5"] >= 0.99
    assert len(doc["screws"]) == 5 and doc["failing_screws"] == []
    assert (phantom_plate / "plate.png").stat().st_size > 10_000


def test_plate_and_bone_model_do_not_interfere(phantom_run, phantom_plate):
    """A Boolean of the plate and the T-spline solid at zero gap: no common volume beyond 0.1 mm^3; the same
    plate pushed 0.5 mm into the bone has one (the Boolean sees an interference when there is one)."""
    from OCP.BRepBuilderAPI import BRepBuilderAPI_Transform
    from OCP.gp import gp_Trsf, gp_Vec

    from bonecad.occ.exchange import read_named_step
    from bonecad.occ.plate import interference_mm3

    bone, _ = read_named_step(phantom_run / "tspline.step")
    plate, _ = read_named_step(phantom_plate / "plate.step")
    assert interference_mm3(plate, bone) <= 0.1
    direction = _xyz(_screws(phantom_plate)[2], "dir")
    move = gp_Trsf()
    move.SetTranslation(gp_Vec(*(0.5 * direction)))
    pushed = BRepBuilderAPI_Transform(plate, move, True).Shape()
    assert interference_mm3(pushed, bone) > 50.0


def test_gap_lifts_the_plate_and_tapered_width_and_hole_count_hold(phantom_run, tmp_path):
    doc = _plate(phantom_run, tmp_path / "gap", "--region", "anteromedial_distal_tibia", "--gap", "1",
                 "--width", "13", "10", "--end-radius", "5", "--holes", "4", "--screw-direction", "transverse")
    assert doc["design"]["width_mm"] == [13.0, 10.0] and len(doc["screws"]) == 4
    fit = doc["fit"]
    assert fit["gap_mm"] == 1.0 and fit["largest_penetration_mm"] == 0.0
    assert fit["share_within_gap_plus_mm"]["0.5"] >= 0.99 and fit["share_within_mm"]["0.5"] < 0.05


def test_per_hole_screw_angles_tilt_the_screws(phantom_run, phantom_plate, tmp_path):
    angles = [a for _ in range(5) for a in ("--screw-angle", "15", "0")]
    _plate(phantom_run, tmp_path / "tilted", "--region", "anteromedial_distal_tibia", *angles)
    normal = np.array([_xyz(r, "dir") for r in _screws(phantom_plate)])
    tilted = np.array([_xyz(r, "dir") for r in _screws(tmp_path / "tilted")])
    turn = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", normal, tilted), -1, 1)))
    assert turn == pytest.approx(15.0, abs=0.5)
    up = np.array(json.loads((phantom_run / "frame.json").read_text())["bone_frame"]["proximal"])
    assert np.all(tilted @ up > normal @ up + 0.2)  # tilted along the plate, towards its proximal end


@pytest.mark.parametrize("flags, message", [
    (["--height", "400", "450", "--angle", "95", "175"], "lies outside the bone"),
    (["--region", "anteromedial_distal_tibia", "--width", "30"], "wider than the bone's face"),
    (["--region", "anteromedial_distal_tibia", "--max-screw-length", "20"], "screw 1 cannot be placed"),
    (["--region", "lateral_distal_femur"], "not on a tibia"),
], ids=["off-the-bone", "too-wide", "screw-too-long", "femur-region"])
def test_bad_input_exits_2_naming_the_problem_and_leaves_nothing(phantom_run, tmp_path, capsys, flags, message):
    out = tmp_path / "out"
    assert main(["plate", str(phantom_run), "--out", str(out), *flags]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists() and list(tmp_path.iterdir()) == []


@pytest.mark.skipif(freecad_command() is None, reason="FreeCAD (freecadcmd) is not installed")
def test_freecad_opens_the_plate(phantom_plate):
    verdict = freecad_check(phantom_plate / "plate.step")
    assert verdict.one_valid_closed_solid, verdict.summary()
    doc = json.loads((phantom_plate / "plate.json").read_text())
    # FreeCAD 0.20.2 integrates the offset-surface top 0.2 % short of OpenCascade 7.9 and plate.stl
    assert verdict.volumes_mm3[0] == pytest.approx(doc["plate"]["volume_mm3"], rel=5e-3)


def _reconstructed(tmp_path_factory, mesh: Path, name: str) -> Path:
    if not mesh.is_file():
        pytest.skip(f"the real bone {mesh} is absent")
    out = tmp_path_factory.mktemp(name) / "out"
    assert main(["reconstruct", str(mesh), "--out", str(out), "-q"]) == 0
    return out


@pytest.fixture(scope="module")
def ct_tibia_run(tmp_path_factory) -> Path:
    return _reconstructed(tmp_path_factory, CT_TIBIA, "ct_tibia_run")


@pytest.fixture(scope="module")
def ct_femur_run(tmp_path_factory) -> Path:
    return _reconstructed(tmp_path_factory, CT_FEMUR, "ct_femur_run")


@pytest.mark.slow
def test_real_tibia_plates(ct_tibia_run, tmp_path):
    """LHDL's tibia, anteromedial plate: transverse screws clear the joint; the default (normal) screws are
    checked, and any that leaves the bone near the joint is flagged with its reason."""
    region = "anteromedial_distal_tibia"
    out = tmp_path / region
    _plate(ct_tibia_run, out, "--region", region, "--screw-direction", "transverse")
    check_plate(out, ct_tibia_run, CT_TIBIA, joints_clear=True)
    doc = _plate(ct_tibia_run, tmp_path / "normal", "--region", region)
    check_plate(tmp_path / "normal", ct_tibia_run, CT_TIBIA, joints_clear=False)
    assert all(f["why"] for f in doc["failing_screws"])


@pytest.mark.slow
def test_real_femur_plate(ct_femur_run, tmp_path):
    out = tmp_path / "femur"
    _plate(ct_femur_run, out, "--region", "lateral_distal_femur", "--screw-direction", "transverse")
    check_plate(out, ct_femur_run, CT_FEMUR, joints_clear=True)


@pytest.mark.slow
def test_plate_straight_from_a_mesh(ct_tibia_run, tmp_path):
    """One command from a mesh file (the T-spline fitted on the way) gives the plate the reconstruction's
    folder gives, within the fit's repeatability."""
    out = tmp_path / "from_mesh"
    doc = _plate(CT_TIBIA, out, "--region", "anteromedial_distal_tibia", "--screw-direction", "transverse")
    check_plate(out, ct_tibia_run, CT_TIBIA, joints_clear=True)
    folder = _plate(ct_tibia_run, tmp_path / "from_folder", "--region", "anteromedial_distal_tibia",
                    "--screw-direction", "transverse")
    assert doc["plate"]["volume_mm3"] == pytest.approx(folder["plate"]["volume_mm3"], rel=0.02)
    assert [s["stock_mm"] for s in doc["screws"]] == pytest.approx([s["stock_mm"] for s in folder["screws"]],
                                                                   abs=2.0)


def test_fracture_screws_hold_each_fragment_and_keep_off_the_fracture(phantom_run, tmp_path):
    """A reduction's two fragments meeting at 45 mm: the hole within 10 mm of the line stays empty, each
    fragment keeps two screws, the working length spans the empty hole; asking three per fragment exits 2."""
    reduction = tmp_path / "reduce"
    reduction.mkdir()
    (reduction / "reduction.json").write_text(json.dumps(
        {"fragments": [{"name": "distal", "height_mm": [-20, 45]}, {"name": "proximal", "height_mm": [45, 400]}]}))
    doc = _plate(phantom_run, tmp_path / "fixed", "--region", "anteromedial_distal_tibia", "--fracture",
                 str(reduction))
    fracture = doc["fracture"]
    assert fracture["fragment_screws"] == {"distal": [1, 2], "proximal": [4, 5]} and fracture["empty_holes"] == [3]
    assert [s["hole"] for s in doc["screws"]] == [1, 2, 4, 5] and doc["plate"]["holes"] == 5
    assert fracture["working_lengths_mm"][0]["working_length_mm"] == pytest.approx(
        2 * doc["design"]["hole_spacing_mm"], abs=0.01)
    assert main(["plate", str(phantom_run), "--region", "anteromedial_distal_tibia", "--out",
                 str(tmp_path / "short"), "--fracture", str(reduction), "--screws-per-fragment", "3", "-q"]) == 2
    assert not (tmp_path / "short").exists()
