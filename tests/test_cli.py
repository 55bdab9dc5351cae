"""The command line: outputs, exit statuses, clear errors, no partial output."""
from __future__ import annotations

import io
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from bonecad.run.cli import main
from bonecad.occ.exchange import read_step

from .conftest import real_mesh_params


@pytest.fixture(scope="module")
def phantom_stl(tmp_path_factory, phantom):
    path = tmp_path_factory.mktemp("in") / "phantom.stl"
    phantom.to_trimesh().export(path)
    return path


def test_frame_writes_json_and_step(phantom_stl, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["frame", str(phantom_stl), "--out", str(out), "-q"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["curves.step", "frame.json"]
    data = json.loads((out / "frame.json").read_text())
    assert data["side"] == "right"
    assert np.allclose(np.linalg.norm(data["mechanical_axis"]["direction"]), 1.0)
    names = {child.label for child in read_step(out / "curves.step").children}
    assert {"mechanical_axis", "lm_plane", "ap_plane", "plateau_centre", "local_proximal_axis"} <= names


def test_frame_boundaries_override(phantom_stl, tmp_path):
    out = tmp_path / "out"
    assert main(["frame", str(phantom_stl), "--out", str(out), "-q", "--distal-boundary", "40",
                 "--proximal-boundary", "280"]) == 0
    regions = json.loads((out / "frame.json").read_text())["regions_mm_above_origin"]
    assert regions["shaft"] == [40.0, 280.0]


def test_inspect_json(phantom_stl, capsys):
    assert main(["inspect", str(phantom_stl), "--json", "-q"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["side"] == "right" and summary["bodies"][0]["role"] == "tibia"


@pytest.mark.parametrize("content", [b"", b"solid x\nfacet normal 0 0 1\n", b"\x00" * 84 + b"\x10" * 50])
def test_bad_input_exit_2_one_line_no_output(tmp_path, capsys, content):
    bad = tmp_path / "bad.stl"
    bad.write_bytes(content)
    out = tmp_path / "out"
    assert main(["frame", str(bad), "--out", str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bad) in err[0]
    assert not out.exists()
    assert not any(p.name.startswith(".out") for p in tmp_path.iterdir())  # no staging folder left


def test_metres_exit_2_names_units_option(phantom, tmp_path, capsys):
    path = tmp_path / "metres.stl"
    trimesh.Trimesh(phantom.vertices / 1000.0, phantom.faces).export(path)
    assert main(["inspect", str(path), "-q"]) == 2
    assert "--units m" in capsys.readouterr().err


def test_console_script_help():
    result = subprocess.run([sys.executable, "-m", "bonecad.run.cli", "--help"], capture_output=True, text=True)
    assert result.returncode == 0
    for command in ("inspect", "frame", "demo"):
        assert command in result.stdout


def test_the_command_ends_at_once_with_its_output_and_status(phantom_stl, tmp_path):
    """The ``bonecad`` command (``cli.entry``) skips Python's teardown: what it printed into a pipe still
    arrives whole (block-buffered when not a terminal), and its exit status is main's."""
    command = [sys.executable, "-m", "bonecad.run.cli"]
    buffered = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}  # as a user's shell has it
    done = subprocess.run([*command, "inspect", str(phantom_stl), "--json"], capture_output=True, text=True,
                          timeout=120, env=buffered)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["triangles"] > 0
    bad = subprocess.run([*command, "inspect", str(tmp_path / "absent.stl")], capture_output=True, text=True,
                         timeout=120, env=buffered)
    assert bad.returncode == 2 and bad.stderr.strip().endswith("file does not exist"), bad.stderr


@pytest.mark.parametrize("path", real_mesh_params())
def test_inspect_real_meshes(path, capsys):
    assert main(["inspect", str(path), "-q"]) == 0
    text = capsys.readouterr().out
    assert "tibia" in text and "side" in text


def test_segment_command(phantom, tmp_path, capsys):
    from bonecad.imaging import mesh_to_ct
    from bonecad.imaging.volume import write_nifti

    ct = write_nifti(mesh_to_ct(phantom.vertices, phantom.faces, voxel_mm=1.5, noise_hu=30.0), tmp_path / "ct.nii.gz")
    out = tmp_path / "tibia.stl"
    assert main(["segment", str(ct), "--out", str(out), "-q"]) == 0
    segmented = trimesh.load(out)
    assert segmented.is_watertight
    assert abs(segmented.volume - phantom.to_trimesh().volume) / phantom.to_trimesh().volume < 0.05
    # A mesh is not a CT volume: exit 2, nothing written.
    mesh = tmp_path / "phantom.stl"
    phantom.to_trimesh().export(mesh)
    assert main(["segment", str(mesh), "--out", str(tmp_path / "again.stl"), "-q"]) == 2
    assert not (tmp_path / "again.stl").exists()


def test_a_ct_input_writes_the_segmented_tibia_beside_the_models(phantom, tmp_path):
    """bone.stl: the polygonal model segmented from the CT, the one the frame (and the models) were built on;
    a mesh input has no such file (the user has it)."""
    from bonecad.imaging import mesh_to_ct
    from bonecad.imaging.volume import write_nifti

    ct = write_nifti(mesh_to_ct(phantom.vertices, phantom.faces, voxel_mm=1.5, noise_hu=30.0), tmp_path / "ct.nii.gz")
    out = tmp_path / "from_ct"
    assert main(["frame", str(ct), "--out", str(out), "-q"]) == 0
    bone = trimesh.load(out / "bone.stl")
    frame = json.loads((out / "frame.json").read_text())
    assert bone.is_watertight and len(bone.faces) == frame["input"]["triangles"]
    assert abs(bone.volume - phantom.to_trimesh().volume) / phantom.to_trimesh().volume < 0.05
    mesh = tmp_path / "phantom.stl"
    phantom.to_trimesh().export(mesh)
    assert main(["frame", str(mesh), "--out", str(tmp_path / "from_mesh"), "-q"]) == 0
    assert not (tmp_path / "from_mesh" / "bone.stl").exists()


def test_a_tibia_segmented_from_a_ct_is_fitted_to_the_stricter_target(phantom):
    """The segmentation's error adds to the fit's: a CT's tibia gets [tspline] segmented_share_within_mm
    (unless the run's own target is stricter); a mesh input keeps the run's target."""
    from dataclasses import replace

    from bonecad.run.bones import bone_settings
    from bonecad.settings import Settings

    settings = Settings.load()
    assert settings.tspline.segmented_share_within_mm == (0.99, 0.12)
    assert bone_settings(phantom, settings).tspline.target_share_within_mm == (0.99, 0.25)
    segmented = replace(phantom, segmented=True)
    assert bone_settings(segmented, settings).tspline.target_share_within_mm == (0.99, 0.12)
    strict = settings.replace("tspline", target_share_within_mm=[0.995, 0.1])
    assert bone_settings(segmented, strict).tspline.target_share_within_mm == (0.995, 0.1)


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_fit_progress_bar_only_on_a_terminal_and_not_with_quiet(monkeypatch):
    """The runner's fit callback drives a bar on stderr when it is a terminal; -q or a pipe: no bar."""
    import argparse

    from bonecad.run.cli import fit_progress
    from bonecad.splines.tspline.fit import FitStats

    stats = FitStats(control_points=264, elements=264, share_within=0.62, max_mm=4.28, rms_mm=0.44)
    terminal = _Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    with fit_progress(argparse.Namespace(quiet=True), 10) as progress:
        assert progress is None
    with fit_progress(argparse.Namespace(quiet=False), 10) as progress:
        assert progress is not None
        progress(0, stats)
        progress(1, stats)
    assert "T-spline fit" in terminal.getvalue() and "2/11" in terminal.getvalue()
    assert "264 control points, 62.0 % within tolerance" in terminal.getvalue()
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    with fit_progress(argparse.Namespace(quiet=False), 10) as progress:
        assert progress is None
