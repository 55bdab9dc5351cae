"""cadquery interop: a bonecad shape used in a cadquery Workplane, sharing the same OCP objects."""
from __future__ import annotations

import numpy as np
import pytest

from bonecad.splines.curve import fit_curve
from bonecad.occ.curves import to_edge
from bonecad.occ.exchange import compound_of, frame_entities
from bonecad.occ.interop import to_cadquery

cadquery = pytest.importorskip("cadquery", reason="cadquery is an optional extra")


def test_frame_entities_in_a_cadquery_workplane(phantom_frame):
    shapes = compound_of(("reference_entities", frame_entities(phantom_frame)))
    workplane = to_cadquery(shapes)
    value = workplane.val()
    assert isinstance(value, cadquery.Shape)
    assert value.wrapped.IsSame(shapes)
    assert len(workplane.faces().vals()) == 4  # L-M, A-P and the two boundary planes


def test_curve_edge_in_cadquery_keeps_its_geometry():
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    curve = fit_curve(np.c_[10 * np.cos(t), 6 * np.sin(t), np.zeros_like(t)], 16, periodic=True).curve
    edge = to_cadquery(to_edge(curve, "section")).val()
    assert edge.geomType() == "BSPLINE"
    assert edge.Length() == pytest.approx(2 * np.pi * np.sqrt((100 + 36) / 2), rel=0.02)
