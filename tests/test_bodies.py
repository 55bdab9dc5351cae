"""Bodies by anatomy in a leg mesh (issue 18): the tibia kept, every other bone named, fused bones refused.

Inputs are built from the four legs of ../shared/data (tibia, femur, patella,
talus in one scanner frame per subject): meshes concatenated with trimesh, or
voxelised together at 1 mm (tests/fused.py) so that bones closer than a voxel
join, as a CT threshold joins them.
"""
from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest

import bonecad
from bonecad.errors import InputError

from .conftest import DATA, ROOT

SUBJECTS = {"LHDL": "LHDL_CT_{}_r", "TLEM2": "TLEM2_CT_{}_r", "ICL": "ICL_MRI_{}_r", "JIA": "JIA_MRI_{}_l"}
FOLDER = {"tibia": "tibia", "femur": "femur", "patella": "leg", "talus": "leg"}
COMBOS = {
    "patella": ("patella",),
    "femur": ("femur",),
    "talus": ("talus",),
    "all": ("patella", "femur", "talus"),
}
FUSED_DEADLINE_S = 60.0


def _bone_file(subject: str, bone: str):
    path = DATA / FOLDER[bone] / (SUBJECTS[subject].format(bone) + ".stl")
    if not path.is_file():
        pytest.skip(f"{path} is absent (the leg meshes of ../shared/data)")
    return path


def _load(subject: str, bone: str):
    import trimesh

    return trimesh.load(_bone_file(subject, bone), force="mesh")


def _tibia_body(subject: str):
    """The tibia alone (the largest body of the tibia file, which may hold the fibula too)."""
    return max(_load(subject, "tibia").split(only_watertight=False), key=lambda b: abs(b.volume))


def _triangles(faces: np.ndarray) -> np.ndarray:
    """Faces as a sorted set of oriented triangles (each rotated to start at its smallest vertex)."""
    rolled = np.stack([np.roll(faces, -k, axis=1) for k in range(3)], axis=1)
    canonical = rolled[np.arange(len(faces)), np.argmin(faces, axis=1)]
    return canonical[np.lexsort(canonical.T[::-1])]


@pytest.fixture(scope="module")
def alone():
    """subject -> the BoneMesh of its tibia file as given (tibia, and the fibula where the file holds it)."""
    return {}


@pytest.mark.parametrize("combo", list(COMBOS))
@pytest.mark.parametrize("subject", list(SUBJECTS))
def test_neighbours_are_named_and_the_tibia_kept(subject, combo, alone, tmp_path):
    import trimesh

    parts = [_load(subject, "tibia")] + [_load(subject, bone) for bone in COMBOS[combo]]
    path = tmp_path / f"{subject}_{combo}.stl"
    trimesh.util.concatenate(parts).export(path)
    bone = bonecad.load_bone(path)
    if subject not in alone:
        alone[subject] = bonecad.load_bone(_bone_file(subject, "tibia"))
    reference = alone[subject]
    # the same tibia body, to the vertex and triangle (cleanup may list the triangles in another order)
    assert np.array_equal(bone.vertices, reference.vertices)
    assert np.array_equal(_triangles(bone.faces), _triangles(reference.faces))
    roles = sorted(b.role for b in bone.bodies if b.role != "fragment")
    expected = sorted(["tibia", *(b.role for b in reference.bodies[1:] if b.role != "fragment"), *COMBOS[combo]])
    assert roles == expected, [(b.role, round(b.volume_mm3 / 1000, 1), round(b.length_mm)) for b in bone.bodies]
    assert bone.bodies[0].role == "tibia"
    for name in COMBOS[combo]:
        assert any(f"{name} (" in r for r in bone.repairs), bone.repairs


def test_cli_frame_and_inspect_report_the_bodies(tmp_path):
    import json

    import trimesh

    from bonecad.run.cli import main

    parts = [_load("ICL", bone) for bone in ("tibia", "patella", "femur", "talus")]
    path = tmp_path / "ICL_leg.stl"
    trimesh.util.concatenate(parts).export(path)
    out = tmp_path / "out"
    assert main(["frame", str(path), "--out", str(out), "-q"]) == 0
    roles = [b["role"] for b in json.loads((out / "frame.json").read_text())["input"]["bodies"]]
    assert roles[0] == "tibia" and sorted(roles[1:]) == ["femur", "fibula", "patella", "talus"]
    result = subprocess.run([sys.executable, "-m", "bonecad.run.cli", "inspect", str(path)],
                            capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert result.returncode == 0, result.stderr
    for role in ("tibia", "femur", "fibula", "patella", "talus"):
        assert role in result.stdout


def _fused(subject: str, neighbour: str, tmp_path):
    import trimesh

    from .fused import fuse_meshes

    tibia, other = _tibia_body(subject), _load(subject, neighbour)
    vertices, faces = fuse_meshes([tibia, other], voxel_mm=1.0)
    mesh = trimesh.Trimesh(vertices, faces)
    largest = max(abs(b.volume) for b in mesh.split(only_watertight=False))
    assert largest > abs(tibia.volume) + 0.9 * abs(other.volume), "the bones did not join at 1 mm voxels"
    path = tmp_path / f"{subject}_tibia_{neighbour}_fused.stl"
    mesh.export(path)
    return path


@pytest.mark.parametrize("subject, neighbour", [("TLEM2", "talus"), ("LHDL", "talus"), ("LHDL", "femur")])
def test_fused_neighbour_is_named(subject, neighbour, tmp_path):
    path = _fused(subject, neighbour, tmp_path)
    with pytest.raises(InputError, match=f"fused to its {neighbour}"):
        bonecad.load_bone(path)


def test_fused_fibula_is_named(fused_tibia_fibula):
    path, _ = fused_tibia_fibula
    with pytest.raises(InputError, match="fused to its fibula") as info:
        bonecad.load_bone(path)
    assert "tibiofibular" in str(info.value)


@pytest.mark.parametrize("neighbour", ["talus", "femur"])
def test_fused_cli_exit_2_no_output(neighbour, tmp_path):
    path = _fused("LHDL", neighbour, tmp_path)
    out = tmp_path / "out"
    started = time.monotonic()
    result = subprocess.run([sys.executable, "-m", "bonecad.run.cli", "reconstruct", str(path), "--out", str(out)],
                            capture_output=True, text=True, cwd=ROOT, timeout=2 * FUSED_DEADLINE_S)
    assert time.monotonic() - started < FUSED_DEADLINE_S
    assert result.returncode == 2, result.stderr
    assert f"fused to its {neighbour}" in result.stderr and "Traceback" not in result.stderr
    assert not out.exists()


@pytest.mark.slow
def test_reconstruct_multi_bone_gives_the_same_tspline(tmp_path, real_tibia_run):
    """ICL's tibia with its patella, femur and talus: the same T-spline (tspline.json) as the tibia alone."""
    import json

    import trimesh

    parts = [_load("ICL", bone) for bone in ("tibia", "patella", "femur", "talus")]
    path = tmp_path / "ICL_leg.stl"
    trimesh.util.concatenate(parts).export(path)
    bonecad.reconstruct(path, tmp_path / "leg")
    leg, alone = (json.loads((folder / "tspline.json").read_text()) for folder in (tmp_path / "leg", real_tibia_run))
    assert leg["tube"] == alone["tube"] and leg["caps"] == alone["caps"]
