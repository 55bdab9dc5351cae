"""Anatomical frame: construction on the phantom, invariance, mirror, real meshes."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from matplotlib.path import Path as PolygonPath
from scipy.spatial.transform import Rotation

import bonecad
from bonecad.errors import InputError
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.mesh.sections import plane_basis, section_mesh

from .conftest import README_SIDES, real_mesh_params


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(abs(a @ b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


def test_phantom_frame_matches_its_construction(phantom_frame):
    f = phantom_frame
    assert f.side == "right"
    assert np.allclose(f.axes @ f.axes.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(f.axes) > 0  # right tibia: (lateral, anterior, proximal) is right-handed
    # The phantom is built in bone coordinates: x lateral, y anterior, z proximal.
    assert f.lateral @ [1, 0, 0] > 0.98
    assert f.anterior @ [0, 1, 0] > 0.98
    assert f.proximal @ [0, 0, 1] > 0.999
    assert 340 < f.mechanical_length_mm < 370
    assert 25 <= f.plateau.semi_axes_mm[0] <= 45 and 15 <= f.plateau.semi_axes_mm[1] <= 30
    assert 0 < f.distal_boundary_mm < f.proximal_boundary_mm < f.mechanical_length_mm


def test_bone_coordinates_round_trip(phantom_frame, rng):
    points = rng.normal(size=(50, 3)) * 100
    assert np.allclose(phantom_frame.to_scanner(phantom_frame.to_bone(points)), points, atol=1e-9)
    assert np.allclose(phantom_frame.to_bone(phantom_frame.plafond_centre[None]), 0.0, atol=1e-9)


def _moved(bone: BoneMesh, rotation: np.ndarray, shift: np.ndarray, mirror: bool = False) -> BoneMesh:
    vertices = bone.vertices @ rotation.T + shift
    faces = bone.faces
    if mirror:
        vertices = vertices * [-1.0, 1.0, 1.0]
        faces = faces[:, ::-1]
    return BoneMesh(vertices=vertices, faces=faces, source="moved")


@settings(max_examples=4, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    quaternion=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.2),
    shift=st.lists(st.floats(-500, 500), min_size=3, max_size=3),
)
def test_rigid_motion_moves_every_entity(phantom, phantom_frame, quaternion, shift):
    rotation = Rotation.from_quat(quaternion).as_matrix()
    shift = np.array(shift)
    moved = bonecad.anatomical_frame(_moved(phantom, rotation, shift))
    f = phantom_frame
    assert moved.side == f.side
    for name in ("lateral", "anterior", "proximal"):
        assert _angle_deg(getattr(moved, name), rotation @ getattr(f, name)) < 0.5, name
    for name in ("plateau_centre", "plafond_centre", "distal_apex", "proximal_apex"):
        assert np.linalg.norm(getattr(moved, name) - (rotation @ getattr(f, name) + shift)) < 0.5, name
    assert np.linalg.norm(moved.local_proximal_axis - (f.local_proximal_axis @ rotation.T + shift), axis=1).max() < 0.5


def test_mirrored_right_tibia_is_left_and_mirrored(phantom, phantom_frame):
    mirrored = bonecad.anatomical_frame(_moved(phantom, np.eye(3), np.zeros(3), mirror=True))
    f = phantom_frame
    flip = np.array([-1.0, 1.0, 1.0])
    assert mirrored.side == "left"
    assert mirrored.mirrored and not f.mirrored
    for name in ("lateral", "anterior", "proximal"):
        assert _angle_deg(getattr(mirrored, name), getattr(f, name) * flip) < 0.5, name
    assert np.linalg.norm(mirrored.plateau_centre - f.plateau_centre * flip) < 0.5
    # In bone coordinates a left tibia looks like the right one.
    assert np.allclose(mirrored.to_bone(phantom.vertices * flip), f.to_bone(phantom.vertices), atol=0.5)


@pytest.mark.parametrize("keep_below_mm", [200.0, 330.0])
def test_partial_bone_is_an_error(phantom, tmp_path, keep_below_mm):
    part = phantom.to_trimesh().slice_plane([0, 0, keep_below_mm], [0, 0, -1.0], cap=True)
    path = tmp_path / "partial.stl"
    part.export(path)
    with pytest.raises(InputError, match="only part of a tibia|whole tibia") as info:
        bonecad.anatomical_frame(bonecad.load_bone(path))
    assert str(path) in str(info.value)


@pytest.mark.parametrize("path", real_mesh_params())
def test_real_meshes_frame_is_plausible(path):
    bone = bonecad.load_bone(path)
    frame = bonecad.anatomical_frame(bone)
    assert frame.side == README_SIDES.get(path.name, "right")
    semi = frame.plateau.semi_axes_mm
    assert 25 <= semi[0] <= 45 and 15 <= semi[1] <= 31, semi
    assert 300 <= frame.mechanical_length_mm <= 420
    # The mechanical axis runs inside the bone all over the shaft.
    u, v = plane_basis(frame.proximal)
    for height in np.linspace(frame.distal_boundary_mm, frame.proximal_boundary_mm, 12):
        point = frame.origin + height * frame.proximal
        loop = section_mesh(bone.vertices, bone.faces, point, frame.proximal).loops()[0]
        polygon = np.column_stack([(loop - point) @ u, (loop - point) @ v])
        assert PolygonPath(polygon).contains_point((0.0, 0.0)), height
    # Where the fibula came with the mesh it lies lateral and posterior: an independent side check.
    for body in bone.bodies:
        if body.role == "fibula":
            x, y, _ = frame.to_bone(body.centroid[None])[0]
            assert x > 10.0 and y < 0.0
