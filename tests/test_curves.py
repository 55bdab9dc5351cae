"""Contour curves: B-spline fitting, sections of the three regions, robustness, STEP round trip."""
from __future__ import annotations

import json

import numpy as np
import pytest

import bonecad
from bonecad.run.cli import main
from bonecad.splines.curve import BSplineCurve, fit_curve
from bonecad.contours.curves import contour_curves
from bonecad.occ.curves import to_geom_curve
from bonecad.occ.exchange import read_step
from bonecad.mesh.bone_mesh import BoneMesh

from .conftest import real_mesh_params
from tests.defaults import SETTINGS
from bonecad.mesh.intake import prepare_bone


def _occ_points(geom, u):
    return np.array([[geom.Value(float(x)).X(), geom.Value(float(x)).Y(), geom.Value(float(x)).Z()] for x in u])


def test_fit_follows_a_cubic_closely(rng):
    """A cubic polynomial curve (about 50 mm long) is followed to well within the curve tolerances."""
    coefficients = rng.normal(size=(4, 3)) * [[1], [30], [20], [10]]
    t = np.sort(rng.uniform(0, 1, 500))
    t[[0, -1]] = 0.0, 1.0
    points = np.stack([t**k for k in range(4)], axis=1) @ coefficients
    fit = fit_curve(points, 12, periodic=False)
    assert fit.max_deviation_mm < 0.02
    assert np.allclose(fit.curve(np.array([0.0, 1.0])), points[[0, -1]], atol=1e-6)


@pytest.mark.parametrize("periodic", [True, False])
def test_fit_converges_on_a_smooth_section(periodic):
    """An analytic bone-like section: 28 control points follow it within 5 microns, error falls like h^4."""
    t = np.linspace(0, 2 * np.pi, 1000, endpoint=False)
    points = np.c_[20 * np.cos(t) + np.cos(5 * t), 12 * np.sin(t) + 2 * np.sin(3 * t), 0.5 * np.sin(2 * t)]
    points = points if periodic else points[:700]
    errors = {count: fit_curve(points, count, periodic=periodic).max_deviation_mm for count in (20, 28, 40)}
    assert errors[28] < 0.005
    assert errors[40] < errors[20] / 5


def test_periodic_curve_is_c2_at_its_seam(rng):
    t = np.linspace(0, 2 * np.pi, 300, endpoint=False)
    points = np.c_[20 * np.cos(t), 12 * np.sin(t) + 2 * np.sin(3 * t), np.zeros_like(t)]
    curve = fit_curve(points, 28, periodic=True).curve
    for nu in range(3):
        assert np.allclose(curve(np.array([0.0]), nu), curve(np.array([1.0 - 1e-12]), nu), atol=1e-6 * 10**nu)


@pytest.mark.parametrize("periodic", [False, True])
def test_occ_curve_equals_numpy_curve(rng, periodic):
    t = np.linspace(0, 2 * np.pi, 200, endpoint=not periodic)
    points = np.c_[10 * np.cos(t), 7 * np.sin(t), np.sin(2 * t)]
    curve = fit_curve(points, 20, periodic=periodic).curve
    u = rng.uniform(0, 1, 100)
    geom = to_geom_curve(curve)
    assert geom.IsPeriodic() == periodic
    assert np.abs(_occ_points(geom, u) - curve(u)).max() < 1e-9


def test_spikes_are_bridged_and_reported():
    t = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    clean = np.c_[15 * np.cos(t), 15 * np.sin(t), np.zeros_like(t)]
    spiked = clean.copy()
    spiked[[50, 51, 200]] *= 1.25  # peaks of about 4 mm, as a hole or artefact makes
    fit = fit_curve(spiked, 28, periodic=True)
    assert fit.outliers == 3
    dense = fit.curve(np.linspace(0, 1, 1000))
    assert np.abs(np.linalg.norm(dense[:, :2], axis=1) - 15).max() < 0.05


def test_phantom_curves_shape(phantom_contours, phantom_frame):
    cs = phantom_contours
    assert len(cs.distal) == 28 and len(cs.proximal) == 28 and len(cs.shaft) >= 4
    assert all(c.curve.count == 40 for c in cs.distal)
    assert all(c.curve.count == 70 for c in cs.proximal)
    assert all(c.curve.count == 28 and c.curve.periodic for c in cs.shaft)
    zd, zp = phantom_frame.distal_boundary_mm, phantom_frame.proximal_boundary_mm
    ends = lambda c: c.curve(np.array([0.0, 1.0]))  # noqa: E731
    for c in cs.distal:
        start, end = ends(c)
        assert np.hypot(*start[:2]) == pytest.approx(2.5, abs=1e-6)  # apex hole about the axis
        assert end[2] == pytest.approx(zd, abs=1e-6)
        angle = np.degrees(np.arctan2(end[1], end[0])) % 360
        assert min(abs(angle - c.angle_deg), 360 - abs(angle - c.angle_deg)) < 1e-6
    for c in cs.proximal:
        assert ends(c)[1][2] == pytest.approx(zp, abs=1e-6)
    # Shaft sections start at angle 0 (lateral, +x) and run lateral -> anterior (counter-clockwise).
    assert [c.level_mm for c in cs.shaft] == sorted(c.level_mm for c in cs.shaft)
    assert cs.shaft[0].level_mm == pytest.approx(zd) and cs.shaft[-1].level_mm == pytest.approx(zp)
    for c in cs.shaft:
        start = c.curve(np.array([0.0]))[0]
        assert start[0] > 0 and start[2] == pytest.approx(c.level_mm, abs=1e-6)
        quarter = c.curve(np.array([0.2]))[0]
        assert quarter[1] > start[1]
    # Where regions meet, shaft curve 0 starts where distal curve 0 ends.
    assert np.linalg.norm(cs.shaft[0].curve(np.array([0.0]))[0] - cs.distal[0].curve(np.array([1.0]))[0]) < 0.05


def test_phantom_tolerances(phantom_contours):
    summary = phantom_contours.summary()
    assert summary["shaft"]["within_tolerance"] == summary["shaft"]["curves"]
    assert summary["proximal"]["within_tolerance"] == summary["proximal"]["curves"]
    # The reported deviation is the measured one: recompute it for one curve.
    c = phantom_contours.distal[5]
    dense = c.curve(np.linspace(0, 1, 20000))
    nearest = np.min(np.linalg.norm(c.raw_points[:, None] - dense[None], axis=2), axis=1)
    assert nearest.max() == pytest.approx(c.max_deviation_mm, abs=0.003)


def test_holes_and_noise(phantom, phantom_frame, phantom_contours, rng):
    """Holes punched in the mesh and noise on it: every curve is still produced and stays near the clean one."""
    mesh = phantom.to_trimesh()
    centres = mesh.triangles_center
    keep = np.ones(len(mesh.faces), dtype=bool)
    for centre in ([0.0, 13.0, 150.0], [-20.0, 0.0, 20.0], [25.0, -10.0, 330.0]):
        keep &= np.linalg.norm(centres - centre, axis=1) > 3.0
    vertices = mesh.vertices + rng.normal(scale=0.05, size=mesh.vertices.shape)
    spiky = rng.choice(len(vertices), 40, replace=False)
    vertices[spiky] += mesh.vertex_normals[spiky] * 3.0
    holed = prepare_bone(vertices, mesh.faces[keep], source="holed phantom", settings=SETTINGS.mesh,
                         plausible=SETTINGS.units)
    assert any("closed holes" in r for r in holed.repairs)
    contours = contour_curves(holed, bonecad.anatomical_frame(holed), settings=SETTINGS.curves)
    assert len(contours.distal) == 28 and len(contours.proximal) == 28
    assert sum(len(c.repairs) > 0 for c in contours.all_curves()) > 0
    clean = {c.name: c for c in phantom_contours.distal + phantom_contours.proximal}
    u = np.linspace(0.05, 0.95, 200)
    for c in contours.distal + contours.proximal:
        reference = clean[c.name].curve(np.linspace(0, 1, 4000))
        distance = np.min(np.linalg.norm(c.curve(u)[:, None] - reference[None], axis=2), axis=1)
        assert np.percentile(distance, 95) < 0.5, c.name


def test_left_tibia_curves_mirror_right(phantom, phantom_contours):
    flip = np.array([-1.0, 1.0, 1.0])
    left = BoneMesh(vertices=phantom.vertices * flip, faces=phantom.faces[:, ::-1], source="mirrored")
    contours = contour_curves(left, bonecad.anatomical_frame(left), settings=SETTINGS.curves)
    for a, b in zip(contours.distal, phantom_contours.distal):
        assert np.abs(a.curve(np.linspace(0, 1, 50)) - b.curve(np.linspace(0, 1, 50))).max() < 0.3


def test_curves_command_and_step_round_trip(phantom, tmp_path):
    mesh_path = tmp_path / "phantom.stl"
    phantom.to_trimesh().export(mesh_path)
    out = tmp_path / "out"
    assert main(["curves", str(mesh_path), "--out", str(out), "-q"]) == 0
    assert {"curves.step", "curves.iges", "curves.json", "curves.png", "frame.json"} <= {p.name for p in out.iterdir()}
    data = json.loads((out / "curves.json").read_text())
    by_name = {c["name"]: c for c in data["curves"]}
    step = read_step(out / "curves.step")
    groups = {child.label: child for child in step.children}
    assert set(groups) == {"contour_curves", "reference_entities"}
    edges = {child.label: child.edges()[0] for child in groups["contour_curves"].children}
    assert set(edges) == set(by_name)
    from OCP.BRep import BRep_Tool

    for name in ("distal_03_30deg", "proximal_10_125deg", "shaft_02_z" + name_level(by_name)):
        stored = by_name[name]
        curve = BSplineCurve(np.array(stored["control_points"]), np.array(stored["knots"]), 3, stored["periodic"])
        geom = BRep_Tool.Curve_s(edges[name].wrapped, 0.0, 1.0)
        assert geom.NbPoles() == curve.count and geom.IsPeriodic() == curve.periodic
        u = np.linspace(0.0, 1.0, 30)
        step_points = _occ_points(geom, u)
        expected = curve(u)
        assert np.abs(step_points - expected).max() < 1e-5, name  # STEP keeps 6+ significant digits


def name_level(by_name):
    return next(n for n in by_name if n.startswith("shaft_02_z")).split("_z")[1]


@pytest.mark.parametrize("path", real_mesh_params())
def test_real_meshes_every_curve(path):
    bone = bonecad.load_bone(path)
    contours = contour_curves(bone, bonecad.anatomical_frame(bone), settings=SETTINGS.curves)
    summary = contours.summary()
    assert summary["distal"]["curves"] == 28 and summary["proximal"]["curves"] == 28
    assert summary["shaft"]["curves"] >= 4
    # Smooth CT meshes: most curves within tolerance; every deviation is small against the bone's size.
    for name in ("distal", "shaft", "proximal"):
        assert summary[name]["worst_max_deviation_mm"] < 1.0
