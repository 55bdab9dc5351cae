"""Mesh intake: formats, cleanup, bodies, units, and clear errors on bad files."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

import bonecad
from bonecad.errors import InputError

from .conftest import real_mesh_params


@pytest.mark.parametrize("suffix", [".stl", ".obj", ".ply", ".off"])
def test_formats_round_trip(phantom, tmp_path, suffix):
    path = tmp_path / f"tibia{suffix}"
    phantom.to_trimesh().export(path)
    bone = bonecad.load_bone(path)
    assert bone.triangle_count == phantom.triangle_count
    assert np.allclose(np.sort(bone.vertices, axis=0), np.sort(phantom.vertices, axis=0), atol=1e-4)
    assert bone.watertight


def test_ascii_stl(phantom, tmp_path):
    path = tmp_path / "ascii.stl"
    path.write_bytes(trimesh.exchange.stl.export_stl_ascii(phantom.to_trimesh()).encode())
    assert bonecad.load_bone(path).triangle_count == phantom.triangle_count


def test_binary_stl_read_as_trimesh_reads_it(phantom, tmp_path):
    """A binary STL is read without trimesh into trimesh's arrays (a corner per vertex, float32); an ASCII STL
    goes to trimesh's reader."""
    from trimesh.exchange.load import mesh_loaders

    from bonecad.mesh.intake import _binary_stl

    path = tmp_path / "binary.stl"
    phantom.to_trimesh().export(path)
    vertices, faces = _binary_stl(path)
    with open(path, "rb") as file:
        loaded = mesh_loaders["stl"](file, file_type="stl")
    assert vertices.dtype == np.float32 and np.array_equal(vertices, np.asarray(loaded["vertices"]).reshape(-1, 3))
    assert np.array_equal(faces, loaded["faces"])
    ascii_path = tmp_path / "ascii.stl"
    ascii_path.write_bytes(trimesh.exchange.stl.export_stl_ascii(phantom.to_trimesh()).encode())
    assert _binary_stl(ascii_path) is None


def _write(tmp_path, name, content: bytes):
    path = tmp_path / name
    path.write_bytes(content)
    return path


@pytest.mark.parametrize(
    "name, content, message",
    [
        ("empty.stl", b"", "empty"),
        ("text.stl", b"this is not a mesh at all\n" * 20, "no triangles|cannot be read"),
        ("nan.obj", b"v nan 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\nf 1 4 2\nf 2 4 3\n", "NaN"),
        ("image.png", b"\x89PNG\r\n", "unsupported mesh format"),
    ],
)
def test_bad_files_raise_input_error(tmp_path, name, content, message):
    path = _write(tmp_path, name, content)
    with pytest.raises(InputError, match=message) as info:
        bonecad.load_bone(path)
    assert str(path) in str(info.value)


def test_truncated_binary_stl(phantom, tmp_path):
    data = trimesh.exchange.stl.export_stl(phantom.to_trimesh())
    path = _write(tmp_path, "cut.stl", data[: len(data) // 3])
    with pytest.raises(InputError) as info:
        bonecad.load_bone(path)
    assert str(path) in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        bonecad.load_bone(tmp_path / "nope.stl")


@pytest.mark.parametrize("unit, scale", [("m", 1e-3), ("cm", 0.1)])
def test_other_units_are_named_and_readable(phantom, tmp_path, unit, scale):
    path = tmp_path / f"in_{unit}.stl"
    trimesh.Trimesh(phantom.vertices * scale, phantom.faces).export(path)
    with pytest.raises(InputError, match=f"--units {unit}"):
        bonecad.load_bone(path)
    bone = bonecad.load_bone(path, units=unit)
    assert np.allclose(np.ptp(bone.vertices, axis=0), np.ptp(phantom.vertices, axis=0), rtol=1e-6)


def test_fragments_and_extra_bodies_are_dropped(phantom, tmp_path):
    fragment = trimesh.creation.icosphere(2, radius=4.0)
    fragment.apply_translation([80.0, 0.0, 150.0])
    whole = trimesh.util.concatenate([phantom.to_trimesh(), fragment])
    path = tmp_path / "with_fragment.stl"
    whole.export(path)
    bone = bonecad.load_bone(path)
    assert bone.triangle_count == phantom.triangle_count
    assert [b.role for b in bone.bodies] == ["tibia", "fragment"]
    assert any("dropped fragment" in r for r in bone.repairs)


def test_broken_tibia_is_an_error(phantom, tmp_path):
    mesh = phantom.to_trimesh()
    lower = mesh.slice_plane([0, 0, 180.0], [0, 0, -1.0], cap=True)
    upper = mesh.slice_plane([0, 0, 185.0], [0, 0, 1.0], cap=True)
    path = tmp_path / "broken.stl"
    trimesh.util.concatenate([lower, upper]).export(path)
    with pytest.raises(InputError, match="broken into 2 large pieces"):
        bonecad.load_bone(path)


def test_holes_are_closed_and_reported(phantom, tmp_path):
    mesh = phantom.to_trimesh()
    centres = mesh.triangles_center
    hole = np.linalg.norm(centres - [0.0, 14.0, 180.0], axis=1) < 3.0
    assert hole.sum() > 3
    path = tmp_path / "holed.stl"
    trimesh.Trimesh(mesh.vertices, mesh.faces[~hole]).export(path)
    bone = bonecad.load_bone(path)
    assert bone.watertight
    assert any("closed holes" in r for r in bone.repairs)


@pytest.mark.parametrize("path", real_mesh_params())
def test_real_meshes_keep_the_tibia(path):
    bone = bonecad.load_bone(path)
    assert bone.watertight
    assert bone.bodies[0].role == "tibia"
    assert 250.0 <= bone.bodies[0].length_mm <= 500.0
    assert all(b.role in {"fibula", "fragment"} for b in bone.bodies[1:])
    assert len(bone.bodies) == (1 if "no_fib" in path.name else 2)


def test_duplicate_and_non_manifold_faces_are_repaired(phantom, tmp_path):
    mesh = phantom.to_trimesh()
    faces = mesh.faces
    # A duplicated face, a degenerate face and a fin sharing an existing edge (non-manifold edge).
    a, b, _ = faces[100]
    extra_vertex = len(mesh.vertices)
    vertices = np.vstack([mesh.vertices, mesh.vertices[a] + [0.0, 0.0, 5.0]])
    broken = np.vstack([faces, faces[:1], [[a, a, b]], [[a, b, extra_vertex]]])
    path = tmp_path / "broken.ply"
    trimesh.Trimesh(vertices, broken, process=False).export(path)
    bone = bonecad.load_bone(path)
    assert bone.watertight and len(bone.bodies) == 1
    assert abs(bone.to_trimesh().volume - mesh.volume) / mesh.volume < 1e-3
    text = " ".join(bone.repairs)
    assert "duplicate faces" in text and ("non-manifold" in text or "degenerate" in text)
