"""The femur (issue 22): recognition (and --bone naming the other bone: exit 2), a leg's femur kept with
--bone femur, frame and landmarks on the four femurs of ../shared/data/femur, rigid-motion equivariance
of the frame and of the fitted T-spline, and the whole pipeline on the smallest CT femur (with its report
and its plate region).

The full reconstruction runs on LHDL_CT_femur_r only (70 k triangles, ~70 s on a quiet machine; a second
femur would cost as much, over the suite's budget); the other three femurs' model figures are measured by
``benchmarks/bench_pipeline.py femurs`` (docs/validation/femurs.md).
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from tests.conftest import DATA

FEMUR_DIR = DATA / "femur"
FEMURS = sorted(FEMUR_DIR.glob("*.stl")) if FEMUR_DIR.is_dir() else []
SIDES = {"JIA_MRI_femur_l": "left"}  # as the data README states them; the others are right femurs

# Hand-picked head regions, determined once by looking at each mesh (scanner mm): a centre near the
# head's, its radius rounded to the mm, and a unit direction from the neck into the head. The region
# is the surface within 3 mm of that sphere and within 100 degrees of that direction: the head clear
# of its junction with the neck (at ~115 degrees: a head covers ~73 % of its sphere). Smaller caps
# give other spheres on the MRI heads, which are not round: a 60-degree cap's centre lies 2.2 (ICL)
# and 3.5 mm (JIA) from the whole head's, its radius 1.4 and 2.5 mm larger (0.6-1.0 mm on the CTs).
HEAD_REGIONS = {
    "LHDL_CT_femur_r": ((144.0, 243.0, -432.0), 23.0, (0.7, -0.3, 0.6)),
    "TLEM2_CT_femur_r": ((-64.0, -147.0, -319.0), 23.0, (0.7, -0.4, 0.6)),
    "ICL_MRI_femur_r": ((80.0, -26.0, 19.0), 26.0, (-0.6, 0.1, 0.8)),
    "JIA_MRI_femur_l": ((88.0, -37.0, -186.0), 19.0, (-0.6, -0.1, 0.8)),
}


def femur_params():
    if not FEMURS:
        return [pytest.param(None, marks=pytest.mark.skip(reason=f"femur folder {FEMUR_DIR} is absent"))]
    return [pytest.param(p, id=p.stem) for p in FEMURS]


@pytest.fixture(scope="module")
def settings():
    from bonecad.settings import Settings

    return Settings.load()


@pytest.fixture(scope="module", params=femur_params())
def femur(request, settings):
    from bonecad.anatomy.femur import femur_frame
    from bonecad.mesh.intake import load_bone

    bone = load_bone(request.param, settings=settings.mesh, plausible=settings.units)
    return request.param.stem, bone, femur_frame(bone, settings=settings.femur)


def _hand_picked_sphere(bone, name):
    """Least-squares sphere (numpy's lstsq on the algebraic form) through the hand-picked head region."""
    centre, radius, direction = HEAD_REGIONS[name]
    centre, direction = np.array(centre), np.array(direction) / np.linalg.norm(direction)
    rel = bone.vertices - centre
    dist = np.linalg.norm(rel, axis=1)
    picked = bone.vertices[(np.abs(dist - radius) < 3.0) & (rel @ direction > np.cos(np.radians(100)) * dist)]
    assert len(picked) > 200
    a = np.column_stack([2 * picked, np.ones(len(picked))])
    sol = np.linalg.lstsq(a, (picked**2).sum(axis=1), rcond=None)[0]
    return sol[:3], float(np.sqrt(sol[3] + sol[:3] @ sol[:3]))


def test_head_centre_matches_a_sphere_fitted_to_the_hand_picked_head(femur):
    name, bone, frame = femur
    centre, radius = _hand_picked_sphere(bone, name)
    assert np.linalg.norm(frame.femur.head.centre - centre) < 1.0
    assert abs(frame.femur.head.radius_mm - radius) < 1.0


def test_side_and_the_landmarks_agree_with_anatomy(femur):
    name, _, frame = femur
    lm = frame.femur
    assert frame.bone == "femur" and frame.side == SIDES.get(name, "right")
    assert 115.0 < lm.neck_shaft_angle_deg < 145.0  # adult femurs: 120-140 degrees
    assert 18.0 < lm.head.radius_mm < 28.0
    assert 70.0 < np.linalg.norm(lm.epicondyles[1] - lm.epicondyles[0]) < 100.0
    # the lateral epicondyle lies lateral, the head proximal and medial
    assert (lm.epicondyles[1] - lm.epicondyles[0]) @ frame.lateral > 0
    head = frame.to_bone(lm.head.centre[None])[0]
    assert head[2] > 0.8 * frame.mechanical_length_mm and head[0] < -20.0
    # the knee centre lies between the posterior condyles
    across = frame.to_bone(lm.condyle_centres)[:, 0]
    knee = frame.to_bone(lm.knee_centre[None])[0, 0]
    assert across[0] < knee < across[1]


def test_isb_frame(femur):
    """Wu et al. 2002: origin at the head centre, y from the epicondyles' midpoint to it, z to the right,
    x = y cross z (anterior); right-handed in every femur."""
    _, _, frame = femur
    lm = frame.femur
    x, y, z = lm.isb_axes
    assert np.allclose(lm.isb_axes @ lm.isb_axes.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(lm.isb_axes) > 0
    up = lm.head.centre - lm.epicondyles.mean(axis=0)
    assert np.allclose(y, up / np.linalg.norm(up))
    right = np.cross(frame.anterior, frame.proximal)  # the subject's right, for either side
    assert z @ right > 0.9 and x @ frame.anterior > 0.9
    tea = lm.epicondyles[1] - lm.epicondyles[0]
    assert abs(tea @ x) < 1e-9 * np.linalg.norm(tea)  # z in the plane of y and the transepicondylar axis


def test_recognition(settings):
    from bonecad.anatomy.recognise import recognise_bone
    from bonecad.mesh.intake import load_bone

    if not FEMURS:
        pytest.skip(f"femur folder {FEMUR_DIR} is absent")
    for path, expected in ((FEMURS[0], "femur"), (DATA / "tibia" / "ICL_MRI_tibia_r.stl", "tibia")):
        bone = load_bone(path, settings=settings.mesh, plausible=settings.units)
        assert recognise_bone(bone, femur=settings.femur, plausible=settings.units) == expected


def test_a_mesh_that_is_neither_exits_2_naming_what_it_looks_like(tmp_path, capsys):
    import trimesh

    from bonecad.run.cli import main

    ball = tmp_path / "ball.stl"
    trimesh.creation.icosphere(subdivisions=4, radius=30.0).export(ball)
    assert main(["frame", str(ball), "--out", str(tmp_path / "out"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "neither a tibia" in err and "60 mm bone" in err and "sphere" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("path, asked, looks", [
    ("femur/ICL_MRI_femur_r.stl", "tibia", "looks like a femur: a 482 mm bone with a 26 mm sphere (a head)"),
    ("tibia/ICL_MRI_tibia_r.stl", "femur", "looks like a tibia: a 394 mm bone with no head"),
])
def test_the_other_bone_asked_for_exits_2_naming_what_the_mesh_looks_like(tmp_path, capsys, path, asked, looks):
    from bonecad.run.cli import main

    mesh = DATA / path
    if not mesh.exists():
        pytest.skip(f"{mesh} is absent")
    assert main(["frame", str(mesh), "--bone", asked, "--out", str(tmp_path / "out"), "-q"]) == 2
    err = capsys.readouterr().err
    assert str(mesh) in err and f"--bone {asked}, but the mesh {looks}" in err
    assert not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def leg_stl(tmp_path_factory):
    """ICL's leg as one mesh file of five bodies (tibia, fibula, femur, patella, talus; the raw MRI meshes)."""
    import trimesh

    from tests.legs import LEGS, leg_files_present

    if not leg_files_present("ICL"):
        pytest.skip(f"ICL's leg files under {DATA} are absent")
    path = tmp_path_factory.mktemp("leg") / "ICL_leg.stl"
    trimesh.util.concatenate([trimesh.load(DATA / name, force="mesh") for name in LEGS["ICL"][0]]).export(path)
    return path


def test_bone_femur_on_a_leg_keeps_the_femur(leg_stl, tmp_path):
    from bonecad.run.cli import main

    assert main(["frame", str(leg_stl), "--bone", "femur", "--out", str(tmp_path / "out"), "-q"]) == 0
    frame = json.loads((tmp_path / "out" / "frame.json").read_text())
    kept, *dropped = frame["input"]["bodies"]
    assert frame["bone"] == "femur" and frame["side"] == "right"
    assert kept["role"] == "femur" and kept["triangles"] == frame["input"]["triangles"] == 29400
    assert sorted(b["role"] for b in dropped) == ["fibula", "patella", "talus", "tibia"]
    assert 24.0 < frame["head"]["radius_mm"] < 28.0


def test_bone_auto_on_a_leg_keeps_the_tibia_and_names_the_femur(leg_stl, tmp_path):
    """--bone auto models a leg by its tibia, as before the femur came; the femur it drops is named, with the
    option that keeps it."""
    from bonecad.run.cli import main

    assert main(["frame", str(leg_stl), "--out", str(tmp_path / "out"), "-q"]) == 0
    frame = json.loads((tmp_path / "out" / "frame.json").read_text())
    assert frame["input"]["bodies"][0]["role"] == "tibia" and "head" not in frame
    dropped = frame["input"]["repairs"][-1]
    assert dropped.startswith("dropped ") and "femur (29400 triangles" in dropped
    assert dropped.endswith("; --bone femur keeps the femur")


@pytest.fixture(scope="module")
def moved_femur(settings):
    """The smallest femur (ICL MRI, 29 k triangles), and the same mesh turned by 89 degrees about a skew axis
    and shifted: (bone, moved bone, rotation matrix, shift in mm)."""
    from scipy.spatial.transform import Rotation

    from bonecad.mesh.intake import load_bone, prepare_bone

    path = FEMUR_DIR / "ICL_MRI_femur_r.stl"
    if not path.exists():
        pytest.skip(f"{path} is absent")
    bone = load_bone(path, settings=settings.mesh, plausible=settings.units)
    rot = Rotation.random(random_state=3).as_matrix()
    shift = np.array([120.0, -40.0, 300.0])
    moved = prepare_bone(bone.vertices @ rot.T + shift, bone.faces, settings=settings.mesh, plausible=settings.units)
    return bone, moved, rot, shift


def test_rigid_motion_moves_every_entity(settings, moved_femur):
    """The frame of a rotated and shifted femur is the rotated and shifted frame (0.5 mm, 0.5 degree)."""
    from bonecad.anatomy.femur import femur_frame

    bone, moved, rot, shift = moved_femur
    frame = femur_frame(bone, settings=settings.femur)
    other = femur_frame(moved, settings=settings.femur)
    move = lambda p: np.asarray(p) @ rot.T + shift  # noqa: E731
    for a, b in ((frame.femur.head.centre, other.femur.head.centre), (frame.origin, other.origin),
                 (frame.femur.knee_centre, other.femur.knee_centre),
                 (frame.local_proximal_axis, other.local_proximal_axis)):
        assert np.abs(move(a) - b).max() < 0.5
    angles = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", frame.axes @ rot.T, other.axes), -1, 1)))
    assert angles.max() < 0.5
    assert abs(frame.distal_boundary_mm - other.distal_boundary_mm) < 0.5
    assert abs(frame.proximal_boundary_mm - other.proximal_boundary_mm) < 0.5
    assert other.side == frame.side


def test_rigid_motion_moves_the_fitted_model(settings, moved_femur):
    """The T-spline fitted to the moved femur is the moved T-spline: the same T-mesh (the local refinement
    marks the same elements) and every control point of the tube and the caps moved (0.5 mm), so every
    surface point is (a T-spline point is a convex combination of its control points). Coarse curves and
    one refinement round keep it to ~4 s a model; the tolerance figures agree too."""
    from bonecad.contours.curves import contour_curves
    from bonecad.run.bones import bone_frame, bone_settings
    from bonecad.tspline_model.model import build_tspline_model

    bone, moved, rot, shift = moved_femur
    coarse = bone_settings(bone, settings).replace("tspline", max_rounds=1, fit_point_spacing_mm=3.0).replace(
        "curves", distal_angles_deg=list(range(0, 360, 30)), proximal_angles_deg=list(range(0, 360, 30)),
        shaft_min_spacing_mm=12.0, distal_control_points=20, proximal_control_points=30, shaft_control_points=16)

    def model(b):
        frame = bone_frame(b, coarse)
        contours = contour_curves(b, frame, settings=coarse.curves)
        return frame, build_tspline_model(b, frame, contours, settings=coarse.tspline,
                                          apex_hole_radius_mm=coarse.curves.apex_hole_radius_mm)

    (frame, m), (other_frame, other) = model(bone), model(moved)
    assert m.fit.stats.control_points > m.fit.history[0].control_points  # the round refined the T-mesh
    a, b = m.tspline.mesh, other.tspline.mesh
    assert np.array_equal(a.s_edges, b.s_edges) and np.array_equal(a.t_edges, b.t_edges)
    assert np.allclose(a.s_lines, b.s_lines, atol=1e-9) and np.allclose(a.t_lines, b.t_lines, atol=1e-9)
    for ts, ts_other in ((m.tspline, other.tspline), *((c.tspline, d.tspline) for c, d in zip(m.caps, other.caps))):
        here = frame.to_scanner(ts.control_points) @ rot.T + shift
        assert np.linalg.norm(here - other_frame.to_scanner(ts_other.control_points), axis=1).max() < 0.5
    s, o = m.fit.stats, other.fit.stats
    assert abs(s.share_within - o.share_within) < 1e-3 and abs(s.max_mm - o.max_mm) < 0.5


@pytest.fixture(scope="module")
def femur_run(tmp_path_factory):
    from bonecad.run.cli import main

    path = FEMUR_DIR / "LHDL_CT_femur_r.stl"
    if not path.exists():
        pytest.skip(f"{path} is absent")
    out = tmp_path_factory.mktemp("femur") / "out"
    assert main(["reconstruct", str(path), "--out", str(out), "-q"]) == 0  # both models
    return out


def test_femur_tspline_meets_the_tolerances_or_says_it_stopped_at_the_noise(femur_run):
    """LHDL's femur: 99 % within 0.25 mm, and its worst spot, 1.14 mm off in an element at the size limit,
    within the data's noise: the fit stops there and the report says so (the unstratified samples had missed
    that spot and reported 0.91 mm, a pass by chance)."""
    report = json.loads((femur_run / "report.json").read_text())
    t = report["summary"]["tspline"]
    assert t["within_mm"]["0.25"] >= 0.99
    if t["max_mm"]["mesh_to_cad"] > 1.0:
        assert t["verdict"] == "stopped at the data's noise", t["reason"]
        assert "beyond the data's noise" in t["reason"] and t["max_mm"]["mesh_to_cad"] <= 1.2
    pairs = report["models"]["tspline"]["continuity"]["summary"]["class_counts_by_face_pair"]
    for pair, counts in pairs.items():
        caps = "apex_cap" in pair
        assert counts["gap"] == counts["C0"] == 0, pair
        assert caps or counts["G1"] == 0, pair  # G2 on every seam but the caps'


@pytest.mark.parametrize("model", ["tspline", "nurbs"])
def test_femur_step_is_one_closed_valid_solid(femur_run, settings, model):
    from bonecad.occ.brep import free_edge_count, is_valid, volume_mm3
    from bonecad.occ.exchange import read_named_step
    from bonecad.mesh.intake import load_bone

    solid, names = read_named_step(femur_run / f"{model}.step")
    assert is_valid(solid) and free_edge_count(solid) == 0
    assert {n for n, _ in names} == {"distal", "shaft", "proximal", "distal_apex_cap", "proximal_apex_cap"}
    volume = load_bone(FEMUR_DIR / "LHDL_CT_femur_r.stl", settings=settings.mesh,
                       plausible=settings.units).to_trimesh().volume
    assert abs(volume_mm3(solid) - volume) / volume < (0.01 if model == "tspline" else 0.05)


def test_femur_frame_json_and_reference_entities(femur_run):
    frame = json.loads((femur_run / "frame.json").read_text())
    assert frame["bone"] == "femur" and frame["side"] == "right"
    assert {"head", "neck_axis", "knee_centre", "posterior_condyles", "transepicondylar_axis",
            "anatomical_axis", "isb_frame"} <= set(frame)
    assert set(frame["mechanical_axis"]) >= {"start_knee_centre", "end_head_centre", "direction", "length_mm"}
    # the apex on the head: where the proximal local axis leaves it, one head radius beyond its centre
    apex, head = np.array(frame["apices"]["proximal"]), frame["head"]
    assert abs(np.linalg.norm(apex - np.array(head["centre"])) - head["radius_mm"]) < 1.5
    step = (femur_run / "curves.step").read_text()
    assert all(f"'{n}'" in step for n in ("head_centre", "knee_centre", "transepicondylar_axis", "isb_z_right"))


def test_tibia_profile_changes_no_setting(settings):
    from bonecad.settings import load_profile

    tibia = load_profile("tibia")
    assert tibia.frame == "tibia" and tibia.wider_end == "proximal"
    assert settings.for_bone(tibia) == settings
    femur = load_profile("femur")
    assert femur.wider_end == "distal" and femur.frame == "femur"
    assert settings.for_bone(femur).tspline.max_rounds == 14  # the profile's own setting, over the defaults
    assert settings.for_bone(femur).curves == settings.curves



def test_femur_report_names_the_femur_and_its_origin(femur_run):
    """The report's heights are above the knee centre (the femur profile's origin), the kept body is the
    femur, and no tibia landmark is named on the page."""
    page = (femur_run / "report.html").read_text()
    assert "mm above the knee centre" in page
    assert "plafond" not in page and "plateau" not in page
    report = json.loads((femur_run / "report.json").read_text())
    assert report["input"]["bodies"][0]["role"] == "femur"


def test_femur_patch_offers_the_femur_regions(femur_run, tmp_path, capsys):
    """A tibia's plate region on a femur exits 2 naming the femur's regions; the lateral distal femur plate's
    footprint is an exact patch of the T-spline that thickens into a valid plate blank."""
    from bonecad.run.cli import main

    assert main(["patch", str(femur_run), "--region", "anteromedial_distal_tibia", "--out", str(tmp_path / "no"),
                 "-q"]) == 2
    assert "not on a femur; the femur's named regions are ['lateral_distal_femur']" in capsys.readouterr().err
    assert not (tmp_path / "no").exists()
    assert main(["patch", str(femur_run), "--region", "lateral_distal_femur", "--out", str(tmp_path / "p"), "-q"]) == 0
    patch = json.loads((tmp_path / "p" / "patch.json").read_text())
    assert patch["plate_blank"]["valid"] and patch["plate_blank"]["solids"] == 1
    assert patch["deviation_from_tspline_mm"] < 1e-6 and patch["deviation_from_mesh"]["max_mm"] < 1.0
