"""Checks of a fitted model's .tsm files, shared by the phantom's and the real tibias' tests."""
from __future__ import annotations

import numpy as np

from bonecad.export.registry import export
from bonecad.splines.tspline import open_region, tsm
from bonecad.tspline_model.cage import FUSION_UNIT_MM, model_cage
from bonecad.tspline_model.model import to_scanner


def assert_model_cage(model, tmp_path) -> tsm.Census:
    """tspline.tsm: one closed, outward cage (sphere topology, the pole faces' eight valence-3 star
    points), re-read exactly; its first vertices are the tube's control points (cm) and its edges
    carry the tube's knot intervals."""
    path = export("tspline", model, tmp_path, only=["tsm"])["tsm"]
    doc = tsm.read(path)
    written = model_cage(model)
    for name in ("faces", "edges", "intervals", "vertices", "links", "grips"):
        assert np.array_equal(getattr(doc, name), getattr(written, name)), name
    info = tsm.census(doc)
    assert (info.euler, info.boundary_loops) == (2, 0) and info.signed_volume > 0
    assert len(info.star_points) == 8 and set(info.valences.values()) == {3}
    assert info.bad_boundary_flags == 0 and dict(doc.header)["end-conditions"] == "MULTIPLE_KNOTS"
    tube = to_scanner(model.tspline, model.frame)
    n = tube.n_control
    assert np.array_equal(doc.grips[:n, :3], tube.control_points / FUSION_UNIT_MM)
    # every tube edge's interval is the knot distance of its two anchors
    params = tube.anchor_params
    lk = doc.links[doc.edges]
    a, b = lk[:, 3], doc.links[lk[:, 2], 3]
    inside = (a < n) & (b < n)
    gap = np.abs(params[a[inside]] - params[b[inside]])
    period = tube.mesh.s_period
    gap[:, 0] = np.minimum(gap[:, 0], period - gap[:, 0])
    assert np.allclose(doc.intervals[inside], gap.max(axis=1), rtol=0, atol=1e-12 * period)
    return info


def assert_open_patch(ts, samples: int = 10_000) -> None:
    """An s/t box of the fitted tube, across the periodic seam, written in the Rhino convention and
    read back, equals the T-spline to 1e-9 mm at ``samples`` points."""
    mesh = ts.mesh
    period = mesh.s_period
    lines, t_lines = mesh.s_lines, mesh.t_lines
    s_a = lines[np.argmin(np.abs(lines - 0.7 * period))]
    s_b = lines[np.argmin(np.abs(lines - 0.25 * period))] + period
    t_a = t_lines[np.argmin(np.abs(t_lines - 0.3 * t_lines[-1]))]
    t_b = t_lines[np.argmin(np.abs(t_lines - 0.6 * t_lines[-1]))]
    region, _ = open_region(ts, (s_a, s_b), (t_a, t_b))
    doc = tsm.parse(tsm.format_document(tsm.rhino_document(region)))
    info = tsm.census(doc)
    assert (info.euler, info.boundary_loops, info.star_points) == (1, 1, ())
    assert info.bad_boundary_flags == 0 and info.boundary_edges_match_ec
    back = tsm.to_tspline(doc)
    rng = np.random.default_rng(7)
    s, t = rng.random(samples) * (s_b - s_a), rng.random(samples) * (t_b - t_a)
    assert np.abs(back.evaluate(s, t).points - ts.evaluate(s + s_a, t + t_a).points).max() < 1e-9
