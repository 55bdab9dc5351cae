"""Apex caps on synthetic tubes: no fold at the pole, whatever the ring row's
control polygon does and whichever way the ring winds (a left tibia's
mirrored frame, a reversed s)."""
from __future__ import annotations

import numpy as np
import pytest

from bonecad.splines.tspline import TSpline
from bonecad.tspline_model.caps import build_cap

RADIUS, LENGTH, N_S = 10.0, 60.0, 16
PERIOD = 2 * np.pi * RADIUS


def tube(*, mirrored: bool, kink: bool) -> TSpline:
    """A cylinder T-spline about z; ``kink`` turns one control point of each
    ring row back past its neighbour (a control polygon that is not
    star-shaped about the pole); ``mirrored`` reflects x (the ring winds the
    other way round the axis)."""
    th = 2 * np.pi * np.arange(N_S) / N_S
    z = np.linspace(0.0, LENGTH, 6)
    th_grid = np.repeat(th[:, None], len(z), axis=1)
    if kink:
        step = 2 * np.pi / N_S
        th_grid[5, 0] -= 1.6 * step
        th_grid[9, -1] -= 1.6 * step
    cp = np.stack([RADIUS * np.cos(th_grid), RADIUS * np.sin(th_grid), np.broadcast_to(z, th_grid.shape)], axis=-1)
    if mirrored:
        cp[..., 0] *= -1.0
    return TSpline.from_grid(np.arange(N_S) * PERIOD / N_S, np.linspace(0.0, LENGTH, 4), cp, s_period=PERIOD)


def _unit(v):
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.mark.parametrize("mirrored", [False, True])
@pytest.mark.parametrize("kink", [False, True])
def test_cap_pole_is_one_tangent_plane_facing_out(mirrored, kink):
    ts = tube(mirrored=mirrored, kink=kink)
    s = np.linspace(0.0, PERIOD, 360, endpoint=False)
    for end, outward, t_ring, r_ring, r_pole in (
        ("distal", np.array([0.0, 0.0, -1.0]), 0.0, 1.0, 0.0),
        ("proximal", np.array([0.0, 0.0, 1.0]), LENGTH, 0.0, 1.0),
    ):
        cap = build_cap(ts, end, np.empty((0, 3)), outward)
        assert cap.pole_spread_deg < 1.0, (end, cap.pole_spread_deg)
        assert cap.ring_angle_deg[0] < 1e-3, (end, cap.ring_angle_deg)
        # the tube's orientation at the ring: its normals against the radial direction
        ring = ts.evaluate(s, np.full(len(s), t_ring), order=1)
        radial = ring.points - ring.points.mean(axis=0)
        radial[:, 2] = 0.0
        tube_sense = np.sign(np.mean(np.einsum("ij,ij->i", _unit(np.cross(ring.du, ring.dv)), _unit(radial))))
        # the cap's normals near the pole all face the same way as the tube's: outward there
        for r in (abs(r_pole - 1e-3), abs(r_pole - 0.05), abs(r_pole - 0.3)):
            near = cap.tspline.evaluate(s, np.full(len(s), r), order=1)
            facing = np.einsum("ij,j->i", _unit(np.cross(near.du, near.dv)), outward) * tube_sense
            assert facing.min() > 0.5, (end, r, facing.min())
        # and the patch meets the tube on the ring
        edge = cap.tspline.evaluate(s, np.full(len(s), r_ring)).points
        assert np.abs(edge - ring.points).max() < 1e-9
