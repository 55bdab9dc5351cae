"""Broken bones (issue 42): the fracture generator, fragment recognition, reduction onto a template, the CLI."""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from bonecad.analysis.reduction import FragmentBody, Template, mirrored, placement_errors, reduce_fragments
from bonecad.errors import InputError
from bonecad.imaging.fracture import FRACTURE_KINDS, apply, combine, fracture_bone
from bonecad.mesh.fragments import load_broken_bone
from bonecad.mesh.intake import load_bone, prepare_bone
from bonecad.settings import Settings

from .conftest import SMALL_REAL_TIBIA

SETTINGS = Settings.load()


def _frustum() -> tuple[np.ndarray, np.ndarray]:
    """A 300 mm long closed 'bone': an elliptic frustum (22 x 15 mm semi-axes distally, twice that proximally)."""
    mesh = trimesh.creation.cylinder(radius=1.0, height=300.0, sections=96)
    mesh = mesh.subdivide_to_size(10.0)
    v = np.asarray(mesh.vertices, dtype=np.float64).copy()
    grow = 1.0 + (v[:, 2] + 150.0) / 300.0
    v[:, 0] *= 22.0 * grow
    v[:, 1] *= 15.0 * grow
    return v, np.asarray(mesh.faces, dtype=np.int64)


@pytest.mark.parametrize("kind", FRACTURE_KINDS)
def test_each_fragment_is_closed_and_together_they_are_the_bone(kind):
    vertices, faces = _frustum()
    volume = trimesh.Trimesh(vertices, faces).volume
    fracture = fracture_bone(vertices, faces, kind=kind, seed=2, rotation_deg=20, translation_mm=15,
                             shortening_mm=10)
    assert [f.role for f in fracture.fragments] == ["proximal", "distal"]
    total = 0.0
    for f in fracture.fragments:
        mesh = trimesh.Trimesh(f.vertices, f.faces, process=False)
        assert mesh.is_watertight and mesh.volume > 0
        total += mesh.volume
        assert 0 < f.fracture.sum() < len(f.faces)
        # the bone's own faces are back on the intact surface once the displacement is undone
        own = f.intact_vertices[np.unique(f.faces[~f.fracture])]
        _, distance, _ = trimesh.proximity.closest_point(trimesh.Trimesh(vertices, faces), own[::60])
        assert distance.max() < 1e-3
    assert total == pytest.approx(volume, rel=1e-4)
    moved = fracture.fragments[1].displacement
    assert np.degrees(np.arccos((np.trace(moved[:3, :3]) - 1) / 2)) == pytest.approx(20.0, abs=1e-6)


def test_a_butterfly_wedge_is_its_share_of_the_volume():
    vertices, faces = _frustum()
    volume = trimesh.Trimesh(vertices, faces).volume
    fracture = fracture_bone(vertices, faces, kind="oblique", butterfly_share=0.03, seed=1)
    roles = [f.role for f in fracture.fragments]
    assert roles == ["proximal", "distal", "butterfly"]
    wedge = trimesh.Trimesh(fracture.fragments[2].vertices, fracture.fragments[2].faces)
    assert wedge.is_watertight
    assert 0.02 <= wedge.volume / volume <= 0.04


@pytest.mark.slow
def test_a_reduction_onto_the_bones_own_shape_undoes_the_displacement():
    """The floor of the method: a template that is the patient's own bone (a perfectly symmetric other side)."""
    vertices, faces = _frustum()
    # an asymmetric bump so that the torsion is defined
    bump = np.exp(-((vertices[:, 2] - 60.0) ** 2 + (vertices[:, 1] - 20) ** 2) / 400.0)
    vertices = vertices + 8.0 * bump[:, None] * np.array([1.0, 0.0, 0.0])
    fracture = fracture_bone(vertices, faces, kind="spiral", seed=4, rotation_deg=20, translation_mm=15,
                             shortening_mm=10)
    bodies = [FragmentBody(f.vertices, f.faces, f.role) for f in fracture.fragments]
    template = Template(*mirrored(*mirrored(vertices, faces, np.zeros(3), np.array([1.0, 0, 0])),
                                  np.zeros(3), np.array([1.0, 0, 0])), "contralateral", "itself", 3.0, 5.0)
    reduction = reduce_fragments(bodies, template, SETTINGS.fracture)
    placed = [apply(r.transform, f.vertices) for r, f in zip(reduction.fragments, fracture.fragments)]
    for mm, deg in placement_errors([f.intact_vertices for f in fracture.fragments], placed):
        assert mm < 0.5 and deg < 0.5
    assert reduction.fragments[0].rotation_deg == pytest.approx(0.0, abs=1e-9)  # the proximal one stays
    assert not any(r.poor for r in reduction.fragments)


def test_a_broken_tibia_is_still_refused_by_reconstruct_and_pointed_to_reduce():
    if not SMALL_REAL_TIBIA.is_file():
        pytest.skip("the shared data folder is absent")
    bone = load_bone(SMALL_REAL_TIBIA, settings=SETTINGS.mesh, plausible=SETTINGS.units)
    fracture = fracture_bone(bone.vertices, bone.faces, kind="transverse", seed=1)
    with pytest.raises(InputError, match="bonecad reduce"):
        prepare_bone(*fracture.mesh(), source="broken.stl", settings=SETTINGS.mesh, plausible=SETTINGS.units)


def _broken_leg(tmp_path, butterfly: float = 0.0):
    """ICL's tibia broken (oblique, seeded), written with its fibula beside it, and its own mirror image."""
    full = trimesh.load(SMALL_REAL_TIBIA)
    bodies = sorted(full.split(only_watertight=False), key=lambda b: -b.volume)
    bone = load_bone(SMALL_REAL_TIBIA, settings=SETTINGS.mesh, plausible=SETTINGS.units)
    vertices = np.asarray(bone.vertices, dtype=np.float64)
    fracture = fracture_bone(vertices, bone.faces, kind="oblique", butterfly_share=butterfly, seed=1,
                             rotation_deg=20, translation_mm=15, shortening_mm=5)
    v, f = combine([fracture.mesh(), *[(np.asarray(b.vertices), np.asarray(b.faces)) for b in bodies[1:]]])
    broken = tmp_path / "broken.stl"
    trimesh.Trimesh(v, f, process=False).export(broken)
    other = tmp_path / "other_side.stl"
    trimesh.Trimesh(*mirrored(vertices, bone.faces, vertices.mean(axis=0), np.array([1.0, 0, 0])),
                    process=False).export(other)
    same = tmp_path / "same_side.stl"
    trimesh.Trimesh(vertices, bone.faces, process=False).export(same)
    return fracture, broken, other, same


@pytest.mark.slow
def test_the_fragments_are_named_by_anatomy(tmp_path):
    if not SMALL_REAL_TIBIA.is_file():
        pytest.skip("the shared data folder is absent")
    fracture, broken, _, _ = _broken_leg(tmp_path, butterfly=0.03)
    read = load_broken_bone(broken, settings=SETTINGS.mesh, plausible=SETTINGS.units, fracture=SETTINGS.fracture)
    assert [p.role for p in read.fragments] == ["proximal", "distal", "intermediate"]
    assert [p.role for p in read.neighbours] == ["fibula"]
    for piece, truth in zip(read.fragments, fracture.fragments):
        assert piece.centroid == pytest.approx(truth.vertices.mean(axis=0), abs=30.0)
    with pytest.raises(InputError, match="nothing to reduce"):
        load_broken_bone(SMALL_REAL_TIBIA, settings=SETTINGS.mesh, plausible=SETTINGS.units,
                         fracture=SETTINGS.fracture)


@pytest.mark.slow
def test_bonecad_reduce_writes_the_reduced_bone_and_refuses_a_same_side_template(tmp_path, capsys):
    if not SMALL_REAL_TIBIA.is_file():
        pytest.skip("the shared data folder is absent")
    from bonecad.run.cli import main

    fracture, broken, other, same = _broken_leg(tmp_path)
    out = tmp_path / "out"
    assert main(["reduce", str(broken), "--template", "contralateral", str(other), "--out", str(out), "-q"]) == 0
    record = json.loads((out / "reduction.json").read_text())
    assert [f["role"] for f in record["fragments"]] == ["proximal", "distal"]
    assert record["neighbours"] == [{"role": "fibula", "volume_mm3": pytest.approx(70819, rel=0.01)}]
    distal = record["fragments"][1]
    assert distal["rotation_deg"] == pytest.approx(20.0, abs=0.5)
    assert distal["registration_rms_mm"] < 0.1 and not distal["poorly_registered"]
    assert distal["neighbours"][0]["overlap_mm"] < 0.1 and distal["neighbours"][0]["gap_mm"] < 0.1
    (line,) = record["fracture_lines_axial_mm"]
    assert distal["axial_extent_mm"][0] == pytest.approx(0.0, abs=1e-6)
    assert line["lowest"] < fracture.level_mm < line["highest"]
    reduced = trimesh.load(out / "reduced.stl")
    intact = trimesh.Trimesh(fracture.intact_vertices, fracture.intact_faces)
    assert reduced.volume == pytest.approx(intact.volume, rel=1e-3)
    _, distance, _ = trimesh.proximity.closest_point(intact, np.asarray(reduced.vertices)[::10])
    assert np.mean(distance) < 0.1  # the proximal fragment stayed, so the reduced bone is the intact one
    assert (out / "reduction.png").stat().st_size > 10_000
    capsys.readouterr()
    assert main(["reduce", str(broken), "--template", "contralateral", str(same), "--out", str(tmp_path / "o2"),
                 "-q"]) == 2
    assert "same side" in capsys.readouterr().err
    assert not (tmp_path / "o2").exists()


def test_a_fracture_images_as_a_ct_with_a_gap_between_the_fragments():
    from bonecad.imaging.fracture import fracture_ct

    vertices, faces = _frustum()
    fracture = fracture_bone(vertices, faces, kind="transverse", seed=0, rotation_deg=0.0, translation_mm=0.0,
                             shortening_mm=-6.0)  # the distal fragment pulled 6 mm away along the axis
    ct = fracture_ct(fracture, voxel_mm=(2.0, 2.0, 2.0), noise_hu=0.0)
    frame = fracture.frame

    def hu_at(height_mm: float) -> float:
        """The CT value on the axis ``height_mm`` above the distal end of the intact bone."""
        point = frame.centre + (frame.bottom + height_mm) * frame.up
        i, j, k = np.round(np.linalg.inv(ct.affine) @ np.r_[point, 1.0])[:3].astype(int)
        return float(ct.hu[k, j, i])

    assert hu_at(fracture.level_mm - 3.0) < 100.0  # soft tissue in the gap
    assert hu_at(fracture.level_mm + 10.0) > 150.0 and hu_at(fracture.level_mm - 16.0) > 150.0  # bone either side


@pytest.mark.slow
def test_the_reduced_bone_is_one_closed_body_its_fracture_surfaces_marked(tmp_path):
    """Onto a template 3 % longer than the bone the fragments land apart: the template bridges the gap, and the
    bridge and the fracture surfaces are the faces left out of the fit and the deviation."""
    if not SMALL_REAL_TIBIA.is_file():
        pytest.skip("the shared data folder is absent")
    from bonecad.run.fracture import reduce_fracture, reduced_solid

    fracture, broken, other, _ = _broken_leg(tmp_path)
    longer = trimesh.load(other)
    centre = longer.vertices.mean(axis=0)
    longer.vertices = (longer.vertices - centre) * np.array([1.0, 1.0, 1.03]) + centre
    longer.export(tmp_path / "longer.stl")
    result = reduce_fracture(broken, "contralateral", tmp_path / "longer.stl", SETTINGS)
    proximal, distal = result.reduction.fragments
    assert [c.neighbour for c in proximal.contacts] == [1]
    assert proximal.contacts[0].gap_mm > 3.0  # the template's extra length, reported
    vertices, faces, excluded = reduced_solid(result)
    solid = trimesh.Trimesh(vertices, faces)
    assert solid.is_watertight and len(solid.split(only_watertight=False)) == 1
    heights = (excluded - fracture.frame.centre) @ fracture.frame.up - fracture.frame.bottom
    assert np.all(np.abs(heights - fracture.level_mm) < 40.0)  # only about the fracture


def test_points_near_a_fracture_surface_get_no_weight_in_the_fit():
    from types import SimpleNamespace

    from bonecad.tspline_model.model import excluded_weights

    frame = SimpleNamespace(to_bone=lambda p: np.asarray(p) - np.array([0.0, 0.0, 10.0]))
    bone = SimpleNamespace(extra={"excluded_centres": np.array([[0.0, 0.0, 10.0]]), "excluded_mm": 1.0})
    points = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 1.5], [5.0, 0.0, 0.0]])
    weights = excluded_weights(points, np.ones(3), bone, frame)  # type: ignore[arg-type]
    assert weights.tolist() == [0.0, 1.0, 1.0]
    assert excluded_weights(points, np.ones(3), SimpleNamespace(extra={}), frame).tolist() == [1.0, 1.0, 1.0]
