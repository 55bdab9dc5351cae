"""Issue 45: a femur is told by its anatomy (the head), never by a length a tibia would have. Femurs of
506-529 mm (tall adults) are framed with --bone auto and --bone femur; one body longer than any single bone
is refused as two bones fused, naming the longest single bone."""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from bonecad.run.cli import main

from .conftest import DATA

PAIRS = DATA / "femur_pairs"
LONG = ["VSD_z009_femur_r", "VSD_z036_femur_l", "VSD_z036_femur_r"]  # 507, 525, 529 mm


@pytest.mark.slow
@pytest.mark.parametrize("stem", LONG)
@pytest.mark.parametrize("asked", ["auto", "femur"])
def test_a_femur_over_500_mm_is_framed(stem, asked, tmp_path, capsys):
    path = PAIRS / f"{stem}.stl"
    if not path.exists():
        pytest.skip(f"{path} is absent")
    assert main(["frame", str(path), "--bone", asked, "--out", str(tmp_path / "out"), "-q"]) == 0
    frame = json.loads((tmp_path / "out" / "frame.json").read_text())
    assert frame["bone"] == "femur"
    assert frame["side"] == ("left" if stem.endswith("_l") else "right")


def test_two_bones_end_to_end_are_refused_as_fused(tmp_path, capsys):
    """A 700 mm body (longer than any tibia or femur) is two bones fused: exit 2, the bound named."""
    bone = trimesh.creation.capsule(height=640.0, radius=30.0)
    bone.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))  # along x
    path = tmp_path / "fused.stl"
    bone.export(path)
    assert main(["frame", str(path), "--out", str(tmp_path / "out"), "-q"]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and "longer than any tibia or femur (at most 620 mm)" in err
    assert "fused to its femur" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_a_half_plane_whose_longest_piece_returns_to_the_apex_still_gives_its_curve(tmp_path):
    """VSD z009's femur (507 mm): near the distal apex the 70 degree half-plane's longest piece of section
    leaves the apex hole and comes back to it; the curve is the piece that runs from the apex to the region
    boundary (this was an internal error, exit 1)."""
    path = PAIRS / "VSD_z009_femur_r.stl"
    if not path.exists():
        pytest.skip(f"{path} is absent")
    assert main(["curves", str(path), "--out", str(tmp_path / "out"), "-q"]) == 0
    curves = json.loads((tmp_path / "out" / "curves.json").read_text())
    assert curves
