"""Settings (bonecad.settings): one typed tree from defaults.toml, a --config file and the flags; every
section reaches its stage (a --config override of each section changes what the run produces)."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from bonecad.errors import InputError
from bonecad.run.cli import main
from bonecad.settings import Settings
from tests.defaults import SETTINGS


def _config(tmp_path, text: str):
    path = tmp_path / "settings.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def phantom_stl(tmp_path_factory, phantom):
    path = tmp_path_factory.mktemp("in") / "phantom.stl"
    phantom.to_trimesh().export(path)
    return path


# --- loading ---------------------------------------------------------------------------------------

def test_defaults_are_typed_and_complete():
    s = Settings.load()
    assert s.curves.distal_angles_deg[:3] == (0.0, 10.0, 20.0)
    assert isinstance(s.tspline.max_control_points, int) and isinstance(s.analysis.band_width_mm, float)
    assert s.pipeline.models == ("nurbs", "tspline")
    assert Settings.load(overrides={k: v for k, v in s.to_dict().items()}) == s


@pytest.mark.parametrize("text, problem", [
    ("[analysis]\nband_widht_mm = 0.2\n", "unknown setting 'analysis.band_widht_mm'"),
    ("[curves]\ndistal_control_points = 'forty'\n", "must be an integer"),
    ("[nurbs]\napex_fill = 'plug'\n", "must be one of"),
    ("[tspline]\ntarget_share_within_mm = [0.99]\n", "must have 2 values"),
    ("[analysis]\nband_width_mm = 0.3\n", "whole number"),
    ("[imaging]\nslice_spline_degree = 0\n", "must be 1 \\(no interpolation\\) to 5"),
    ("analysis = 3\n", "must be a table"),
    ("[curves\n", "cannot read configuration"),
])
def test_a_bad_file_is_an_input_error_naming_it(tmp_path, text, problem):
    path = _config(tmp_path, text)
    with pytest.raises(InputError, match=problem) as info:
        Settings.load(path)
    assert info.value.path == str(path)


def test_flags_override_the_file(tmp_path):
    path = _config(tmp_path, "[nurbs]\napex_fill = 'patch'\n[tspline]\nmax_rounds = 3\n")
    s = Settings.load(path, {"nurbs": {"apex_fill": "ring"}})
    assert s.nurbs.apex_fill == "ring" and s.tspline.max_rounds == 3
    assert s.replace("tspline", max_rounds=4).tspline.max_rounds == 4


# --- each section reaches its stage ------------------------------------------------------------------

def _run(args, capsys) -> tuple[int, str]:
    code = main([*map(str, args), "-q"])
    return code, capsys.readouterr().err


def test_units_section_reaches_the_intake(phantom_stl, tmp_path, capsys):
    assert _run(["frame", phantom_stl, "--out", tmp_path / "a"], capsys)[0] == 0
    config = _config(tmp_path, "[units]\ntibia_length_mm = [420.0, 500.0]\n")
    code, err = _run(["frame", phantom_stl, "--out", tmp_path / "b", "--config", config], capsys)
    assert code == 2 and "420-500 mm" in err and not (tmp_path / "b").exists()


def test_mesh_section_reaches_the_intake(phantom, tmp_path, capsys):
    """A small body well beyond the plateau: a fragment (dropped) at the shipped 2 % share, a piece of a
    broken tibia (an error) when fragments must be under 0.1 % of the tibia's volume."""
    tibia = phantom.to_trimesh()
    top = tibia.vertices[np.argmax(tibia.vertices[:, 2])]
    ball = trimesh.creation.icosphere(subdivisions=3, radius=6.0)
    ball.apply_translation(top + [0.0, 0.0, 40.0])
    path = tmp_path / "tibia_and_fragment.stl"
    trimesh.util.concatenate([tibia, ball]).export(path)
    assert _run(["frame", path, "--out", tmp_path / "a"], capsys)[0] == 0
    roles = [b["role"] for b in json.loads((tmp_path / "a" / "frame.json").read_text())["input"]["bodies"]]
    assert roles == ["tibia", "fragment"]
    config = _config(tmp_path, "[mesh]\nfragment_volume_share = 0.001\n")
    code, err = _run(["frame", path, "--out", tmp_path / "b", "--config", config], capsys)
    assert code == 2 and "broken into 2 large pieces" in err


def test_imaging_section_reaches_the_segmentation(phantom, tmp_path, capsys):
    """A surface level clamped to 900-1000 HU (the shipped clamp, 350-1000 HU, leaves the automatic level
    half-way between the phantom's 1500 HU cortex and its tissue, 760 HU) puts the segmented surface inside
    the bone (2 % less volume)."""
    from bonecad.imaging import mesh_to_ct
    from bonecad.imaging.volume import write_nifti

    ct = write_nifti(mesh_to_ct(phantom.vertices, phantom.faces, voxel_mm=1.5, noise_hu=30.0), tmp_path / "ct.nii.gz")
    assert _run(["segment", ct, "--out", tmp_path / "a.stl"], capsys)[0] == 0
    config = _config(tmp_path, "[imaging]\nlevel_range_hu = [900.0, 1000.0]\n")
    assert _run(["segment", ct, "--out", tmp_path / "b.stl", "--config", config], capsys)[0] == 0
    shipped, clamped = (trimesh.load(tmp_path / name).volume for name in ("a.stl", "b.stl"))
    assert abs(shipped - phantom.to_trimesh().volume) < 0.05 * shipped and clamped < 0.99 * shipped


def test_anatomy_section_reaches_the_frame(phantom_stl, tmp_path, capsys):
    def boundaries(out):
        return json.loads((out / "frame.json").read_text())["regions_mm_above_origin"]

    assert _run(["frame", phantom_stl, "--out", tmp_path / "a"], capsys)[0] == 0
    config = _config(tmp_path, "[anatomy]\ndistal_flare_ratio = 1.3\nproximal_boundary_mm = 250.0\n")
    assert _run(["frame", phantom_stl, "--out", tmp_path / "b", "--config", config], capsys)[0] == 0
    default, changed = boundaries(tmp_path / "a"), boundaries(tmp_path / "b")
    assert changed["shaft"][1] == 250.0 != default["shaft"][1]
    assert changed["distal"][1] > default["distal"][1]  # a lower flare ratio: the shaft starts higher


def test_curves_section_reaches_the_contours(phantom_stl, tmp_path, capsys):
    config = _config(tmp_path, "[curves]\ndistal_control_points = 30\nproximal_angles_deg = [0, 90, 180, 270]\n")
    assert _run(["curves", phantom_stl, "--out", tmp_path / "out", "--config", config], capsys)[0] == 0
    curves = json.loads((tmp_path / "out" / "curves.json").read_text())["curves"]
    assert {len(c["control_points"]) for c in curves if c["region"] == "distal"} == {30}
    assert [c["angle_deg"] for c in curves if c["region"] == "proximal"] == [0.0, 90.0, 180.0, 270.0]


@pytest.fixture(scope="module")
def configured_run(phantom_stl, tmp_path_factory):
    """One reconstruction with [nurbs], [analysis] and [pipeline] overridden in a --config file."""
    folder = tmp_path_factory.mktemp("configured")
    config = folder / "settings.toml"
    config.write_text("[nurbs]\napex_fill = 'patch'\n[analysis]\nband_width_mm = 0.25\nband_limit_mm = 1.0\n"
                      "[pipeline]\nmodels = ['nurbs']\n")
    out = folder / "out"
    assert main(["reconstruct", str(phantom_stl), "--out", str(out), "--config", str(config), "-q"]) == 0
    return out, json.loads((out / "report.json").read_text())


def test_nurbs_section_reaches_the_nurbs_model(configured_run):
    _, report = configured_run
    info = report["models"]["nurbs"]["info"]
    assert info["apex_fill"] == "patch" and set(info["patch_errors"]) == {"distal_apex_cap", "proximal_apex_cap"}


def test_analysis_section_reaches_the_report(configured_run):
    _, report = configured_run
    edges = report["models"]["nurbs"]["deviation"]["mesh_to_cad"]["histogram"]["edges_mm"]
    assert np.allclose(edges, np.linspace(-1.0, 1.0, 9))  # 0.25 mm bands to +-1 mm (shipped: 0.1 to +-2)


def test_pipeline_section_reaches_the_runner(configured_run):
    out, report = configured_run
    assert list(report["models"]) == ["nurbs"]
    assert not any(p.name.startswith("tspline") for p in out.iterdir())


def test_tspline_section_reaches_the_fit(phantom, phantom_frame, phantom_contours):
    from bonecad.tspline_model.model import build_tspline_model

    settings = replace(SETTINGS.tspline, max_control_points=300, max_rounds=2)
    model = build_tspline_model(phantom, phantom_frame, phantom_contours, settings=settings,
                                apex_hole_radius_mm=SETTINGS.curves.apex_hole_radius_mm)
    assert model.control_points <= 300 and len(model.fit.history) <= 3
    assert model.fit.stopped and not model.fit.converged
