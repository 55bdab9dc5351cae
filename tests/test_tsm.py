"""The .tsm (#TS0200) T-spline format: the four real samples, malformed files (exit 2 with the
line), the Rhino convention's exact round trip, the invariants of every written file."""
from __future__ import annotations

import re

import numpy as np
import pytest
from scipy.interpolate import BSpline

from bonecad.run.cli import main
from bonecad.splines.tspline import KnotSegment, TSpline, insert_segments, open_region, tsm

from .conftest import DATA

TSM_DIR = DATA / "tsm"
SAMPLES = sorted(TSM_DIR.glob("*.tsm")) if TSM_DIR.is_dir() else []
needs_samples = pytest.mark.skipif(not SAMPLES, reason=f"the .tsm samples folder {TSM_DIR} is absent")


def sample(name: str) -> tsm.TSMDocument:
    return tsm.read(TSM_DIR / f"{name}.tsm")


def assert_same_document(a: tsm.TSMDocument, b: tsm.TSMDocument) -> None:
    """Topology, knot intervals, grips and grip map identical (bit for bit)."""
    for name in ("faces", "edges", "intervals", "vertices", "directions", "links", "edge_conditions", "grips",
                 "grip_owner", "grip_primary"):
        assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=name == "intervals"), name
    assert a.compound == b.compound and a.header == b.header and a.footer == b.footer


def assert_sound(doc: tsm.TSMDocument, *, euler: int, loops: int) -> tsm.Census:
    """The invariants of TSM.md section 9 on a written document (``check`` ran when it was parsed)."""
    back = tsm.parse(tsm.format_document(doc))
    assert_same_document(doc, back)
    info = tsm.census(back)
    assert (info.euler, info.boundary_loops) == (euler, loops)
    assert info.bad_boundary_flags == 0 and info.boundary_edges_match_ec
    if loops == 0:
        assert info.signed_volume > 0  # outward faces
    return info


@needs_samples
@pytest.mark.parametrize("path", SAMPLES, ids=lambda p: p.stem)
def test_samples_read_and_write_back_the_same(path):
    doc = tsm.read(path)
    text = tsm.format_document(doc)
    assert_same_document(doc, tsm.parse(text))
    assert tsm.format_document(tsm.parse(text)) == text


@needs_samples
@pytest.mark.parametrize("name, counts", [
    ("fusion_cyl8x4_open_readback", (32, 72, 40, 0, 2, 0)),
    ("fusion_cyl8x4_capped_readback", (40, 80, 42, 2, 0, 8)),
    ("fusion_grid3x3_readback", (9, 24, 16, 1, 1, 0)),
    ("rhino_simple_2x2_tjunction", (3, 10, 8, 1, 1, 0)),
])
def test_sample_topology(name, counts):
    info = tsm.census(sample(name))
    assert (info.faces, info.edges, info.vertices, info.euler, info.boundary_loops, len(info.star_points)) == counts
    assert info.bad_boundary_flags == 0 and info.boundary_edges_match_ec
    if name == "fusion_cyl8x4_capped_readback":
        assert set(info.valences.values()) == {3} and info.signed_volume > 0  # 8 valence-3 points, outward
    assert info.t_junctions == (1 if name.startswith("rhino") else 0)


@needs_samples
def test_rhino_sample_evaluates_to_the_clamped_surface_of_its_grips():
    doc = sample("rhino_simple_2x2_tjunction")
    ts = tsm.to_tspline(doc)
    g = doc.grips[:, :3]
    u = np.linspace(0.0, 1.0, 101)
    zero, one = np.zeros_like(u), np.ones_like(u)
    half = np.array([0, 0, 0, 0, 0.5, 1, 1, 1, 1.0])
    # boundary curves: clamped cubics of the boundary vertices' primary and secondary grips
    curves = [((u, zero), BSpline(half, g[[0, 1, 2, 3, 4]], 3)), ((zero, u), BSpline(half, g[[0, 5, 10, 15, 19]], 3)),
              ((one, u), BSpline(half, g[[4, 9, 14, 18, 22]], 3)),
              ((u, one), BSpline(np.array([0, 0, 0, 0, 1, 1, 1, 1.0]), g[[19, 20, 21, 22]], 3))]
    for (s, t), curve in curves:
        assert np.abs(ts.evaluate(s, t).points - curve(u)).max() < 1e-12
    # the grips sit on the Greville rows of the clamped knots: y is linear in t (linear precision)
    rng = np.random.default_rng(0)
    s, t = rng.random(2000), rng.random(2000)
    assert np.abs(ts.evaluate(s, t).points[:, 1] - 30.0 * t).max() < 1e-12
    assert np.abs(ts.evaluate(s, t).points - ts.evaluate_direct(s, t)).max() < 1e-12


def periodic_tube(rng) -> TSpline:
    """A refined tube (periodic s, clamped t) with T-junctions, random wobble."""
    s_knots = np.arange(8) * 2.5
    t_knots = np.array([0.0, 3.0, 5.0, 9.0, 12.0])
    angle = 2 * np.pi * np.arange(8) / 8
    rows = np.linspace(0.0, 12.0, 7)
    cp = np.stack([np.cos(angle)[:, None] * 5 + 0 * rows, np.sin(angle)[:, None] * 5 + 0 * rows,
                   np.broadcast_to(rows, (8, 7))], axis=-1) + 0.2 * rng.standard_normal((8, 7, 3))
    ts = TSpline.from_grid(s_knots, t_knots, cp, s_period=20.0)
    return insert_segments(ts, [KnotSegment("s", 3.75, 3.0, 9.0), KnotSegment("t", 7.0, 2.5, 7.5)]).tspline


def test_rhino_round_trip_of_a_periodic_tube_is_exact(rng, tmp_path):
    ts = periodic_tube(rng)
    doc = tsm.rhino_document(ts)
    info = assert_sound(doc, euler=0, loops=2)
    assert info.t_junctions > 0 and not info.star_points
    path = tsm.write_tspline(ts, tmp_path / "tube.tsm")
    back = tsm.read_tspline(path)
    m, n = ts.mesh, back.mesh
    assert np.array_equal(m.s_edges, n.s_edges) and np.array_equal(m.t_edges, n.t_edges)
    assert np.array_equal(back.control_points, ts.control_points) and np.array_equal(back.weights, ts.weights)
    assert np.allclose(n.s_lines, m.s_lines, rtol=0, atol=1e-12) and np.allclose(n.t_lines, m.t_lines, atol=1e-12)
    assert n.s_period == m.s_period
    s, t = rng.random(500) * 20.0, rng.random(500) * 12.0
    assert np.abs(back.evaluate(s, t).points - ts.evaluate(s, t).points).max() < 1e-9


def test_open_region_in_the_rhino_convention_matches_the_surface(rng):
    ts = periodic_tube(rng)
    region, _ = open_region(ts, (15.0, 27.5), (3.0, 12.0))  # across the periodic seam
    doc = tsm.rhino_document(region)
    assert_sound(doc, euler=1, loops=1)
    back = tsm.to_tspline(tsm.parse(tsm.format_document(doc)))
    s, t = rng.random(10_000) * 12.5, rng.random(10_000) * 9.0
    assert np.abs(back.evaluate(s, t).points - ts.evaluate(s + 15.0, t + 3.0).points).max() < 1e-9


def run_cli(capsys, path, tmp_path) -> tuple[int, str]:
    code = main(["convert", str(path), "--out", str(tmp_path / "out")])
    return code, capsys.readouterr().err


def test_convert_writes_step(tmp_path, capsys, rng):
    from bonecad.occ.exchange import read_step

    path = tsm.write_tspline(periodic_tube(rng), tmp_path / "tube.tsm")
    code, err = run_cli(capsys, path, tmp_path)
    assert code == 0, err
    assert read_step(tmp_path / "out" / "tspline.step").faces()


@needs_samples
@pytest.mark.parametrize("name, problem", [
    ("fusion_cyl8x4_capped_readback", "star point"),
    ("fusion_cyl8x4_open_readback", "without a grip map"),
])
def test_convert_refuses_files_outside_bonecads_rules(name, problem, tmp_path, capsys):
    code, err = run_cli(capsys, TSM_DIR / f"{name}.tsm", tmp_path)
    assert code == 2 and problem in err and name in err
    assert not (tmp_path / "out").exists()


def broken(tmp_path, text: str) -> object:
    path = tmp_path / "broken.tsm"
    path.write_text(text)
    return path


@needs_samples
@pytest.mark.parametrize("edit, expected", [
    (lambda lines: lines[: len(lines) // 2], r"line \d+: expected the footer .* truncated"),
    (lambda lines: lines[:14] + [lines[14][:3]] + lines[15:], "line 15: expected 2 fields after 'e'"),
    (lambda lines: ["#TS0100"] + lines[1:], "line 1: expected the header '#TS0200', got '#TS0100'"),
    (lambda lines: [x.replace("l 11 14 1 0 0 0 0", "l 11 14 99 0 0 0 0") for x in lines],
     "line 29: opposite link 99 is not defined"),
    (lambda lines: [x.replace("e 9 1", "e 9 0.75") for x in lines], "line 10: face 2: inconsistent knot intervals"),
])
def test_malformed_files_exit_2_with_the_line_and_the_problem(edit, expected, tmp_path, capsys):
    lines = (TSM_DIR / "rhino_simple_2x2_tjunction.tsm").read_text().splitlines()
    path = broken(tmp_path, "\n".join(edit(lines)) + "\n")
    code, err = run_cli(capsys, path, tmp_path)
    assert code == 2
    assert str(path) in err
    assert re.search(expected, err), err
    assert not (tmp_path / "out").exists()
