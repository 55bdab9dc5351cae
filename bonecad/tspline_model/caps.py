"""Apex caps: fill the two apex holes of the tube with quad-topology patches.

Each cap is a bicubic B-spline patch P(s, r), periodic in s on exactly the
s-knots of the tube's ring, one Bezier span in r, with rows of control points
(from the pole to the ring):

    row 0: the apex point A (all equal: the pole, where the patch's quads
           degenerate to triangles in space; an extraordinary point of
           valence = number of ring elements);
    row 1: A + v_i, v_i in the plane through A perpendicular to the cap normal
           n  ->  one tangent plane at the pole (G1 at the pole);
    row 2: R0_i - mu D_i  (R0: the tube's ring row; D_i = 3 (R1_i - R0_i) / h_i,
           R1 the next row, h_i the first knot interval on anchor i's s-line)
    row 3: R0_i, the tube's ring row  ->  the same boundary curve (G0).

Rows 2-3 make the cap's cross-boundary derivative 3 mu times the tube's
(sum_i N_i(s) D_i): the two derivatives are parallel and
point the same way all along the ring, so the tangent planes agree exactly:
G1 (in fact C1 after a linear reparameterisation) across the ring. Curvature
is not matched: the ring is G1, not G2. ``ring_normal_angles`` measures it.

The pole height comes from the mesh points inside the hole (a quadratic height
field over the cap plane, evaluated at the axis).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bonecad.splines.lsq import least_squares
from bonecad.splines.tspline import KnotSegment, TSpline, insert_segments


@dataclass(frozen=True)
class ApexCap:
    """One cap: the patch (a tensor-product T-spline), its end, its continuity measures.

    end : "distal" or "proximal". ring_angle_deg : (max, mean) normal angle
    across the ring edge (degrees). pole_spread_deg : largest angle between
    normals at the pole approached from different s (0 = one tangent plane).
    """

    end: str
    tspline: TSpline
    normal: np.ndarray
    ring_angle_deg: tuple[float, float]
    pole_spread_deg: float


def _boundary_rows(tube: TSpline, end: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """s-lines of the ring, the tube's ring row R0 and its cross-derivative row D (ordered by s).

    The tube's derivative across the ring is sum_i N_i(s) D_i with
    D_i = 3 (R1_i - R0_i) / h_i, R1 the next row and h_i the first knot
    interval along anchor i's own s-line (local refinement makes it differ
    from line to line); D_i points into the tube.
    """
    mesh = tube.mesh
    t_n = mesh.shape[1]
    j0, j1 = (2, 3) if end == "distal" else (t_n - 3, t_n - 4)
    a = mesh.anchors
    r0 = np.flatnonzero(a[:, 1] == j0)
    r1 = np.flatnonzero(a[:, 1] == j1)
    r0 = r0[np.argsort(a[r0, 0])]
    r1 = r1[np.argsort(a[r1, 0])]
    if not np.array_equal(a[r0, 0], a[r1, 0]):
        raise ValueError("the tube's two boundary rows must share their s-lines")
    t_idx = mesh.anchor_knots[1][r1]
    tv = mesh.t_lines[t_idx]
    h = tv[:, 3] - tv[:, 2] if end == "distal" else tv[:, 2] - tv[:, 1]
    p0, p1 = tube.control_points[r0], tube.control_points[r1]
    return a[r0, 0], p0, 3.0 * (p1 - p0) / h[:, None]


def build_cap(tube: TSpline, end: str, hole_points: np.ndarray, outward: np.ndarray) -> ApexCap:
    """The cap of one end (see the module docstring); bone coordinates, mm.

    hole_points : (m, 3) mesh points inside the hole (for the pole height).
    outward : (3,) rough outward direction at this apex (the axis direction).
    """
    lines, r0, deriv = _boundary_rows(tube, end)
    mesh = tube.mesh
    if mesh.s_period is None:
        raise ValueError("build_cap: the tube must be periodic in s")
    s_knots = mesh.s_value(lines)
    t_ring = mesh.t_range[0] if end == "distal" else mesh.t_range[1]
    ring = tube.evaluate(np.linspace(*mesh.s_range, 256, endpoint=False), np.full(256, t_ring)).points
    centre = ring.mean(axis=0)
    # cap plane: the plane best fitting the ring, normal oriented outwards
    _, _, vt = np.linalg.svd(ring - centre)
    n = vt[2] * np.sign(vt[2] @ outward)
    e1 = vt[0]
    e2 = np.cross(n, e1)
    height = 0.0
    if len(hole_points) >= 6:
        q = hole_points - centre
        x, y, z = q @ e1, q @ e2, q @ n
        design = np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])
        height = float(least_squares(design, z)[0])
    apex = centre + height * n
    rad = np.linalg.norm(ring - centre, axis=1).mean()
    spokes = _pole_spokes(r0 - centre, s_knots, mesh.s_period, n, e1, e2)
    # cap row 2 = R0 - mu D: the cap's derivative into the ring is 3 mu D, parallel to the tube's
    mu = rad / (3.0 * np.mean(np.linalg.norm(deriv, axis=1)))
    rows = [np.repeat(apex[None], len(r0), axis=0), apex + spokes / 3.0, r0 - mu * deriv, r0]
    if end == "proximal":
        rows = rows[::-1]  # r from the ring to the pole keeps the patch normal outward
    cp = np.stack(rows, axis=1)  # (m_s, 4, 3)
    cap = TSpline.from_grid(s_knots, [0.0, 1.0], cp, s_period=mesh.s_period)
    cap = _match_ring_elements(cap, tube, end)
    angles, spread = _measure(cap, tube, end)
    return ApexCap(end, cap, n, angles, spread)


def _pole_spokes(radial: np.ndarray, s_knots: np.ndarray, period: float, n: np.ndarray, e1: np.ndarray,
                 e2: np.ndarray) -> np.ndarray:
    """Row-1 offsets from the pole: (m, 3) vectors in the cap plane that turn
    monotonically round the pole, one full turn, in the ring's winding sense.

    The pole's degenerate quads have the normal of ds(row 1) x (row 1 - apex)
    there, so row 1 must be star-shaped about the pole with angles rising
    with s: taking it from the ring row's own control points folds the cap
    (normals flip at the pole, 180 degrees of spread) wherever that control
    polygon turns back on itself, as a fit to a noisy or staircase mesh
    makes it do on a 2.5 mm ring. The spokes keep the ring points' mean
    radius and mean phase, and an angle proportional to s (s is the angle
    about the end's axis, scaled to mm).
    """
    x, y = radial @ e1, radial @ e2
    actual = np.arctan2(y, x)
    # winding sense of the ring row (a mirrored frame or a reversed s turns it)
    sense = 1.0 if np.sum(np.angle(np.exp(1j * np.diff(np.append(actual, actual[0]))))) >= 0 else -1.0
    nominal = sense * 2.0 * np.pi * (s_knots - s_knots[0]) / period
    phase = np.angle(np.mean(np.exp(1j * (actual - nominal))))
    phi = nominal + phase
    r = np.mean(np.hypot(x, y))
    return r * (np.cos(phi)[:, None] * e1[None, :] + np.sin(phi)[:, None] * e2[None, :])


def _match_ring_elements(cap: TSpline, tube: TSpline, end: str) -> TSpline:
    """Insert (exactly) the s-breaks of the tube's ring elements, so the cap's
    Bezier faces meet the tube's one to one along the ring."""
    ext = tube.extraction
    period = tube.mesh.s_period
    if period is None:
        raise ValueError("the tube must be periodic in s")
    t_ring = tube.mesh.t_range[0] if end == "distal" else tube.mesh.t_range[1]
    col = 2 if end == "distal" else 3
    on_ring = ext.index_bounds[:, col] == (3 if end == "distal" else tube.mesh.shape[1] - 4)
    on_ring &= np.isclose(ext.t_bounds[:, 0 if end == "distal" else 1], t_ring)
    breaks = np.unique(np.mod(ext.s_bounds[on_ring, 0], period))
    have = cap.mesh.s_lines
    new = [b for b in breaks if np.min(np.abs(have - b)) > 1e-9 * period]
    if not new:
        return cap
    segs = [KnotSegment("s", float(b), 0.0, 1.0) for b in new]
    return insert_segments(cap, segs).tspline


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)


def _measure(cap: TSpline, tube: TSpline, end: str, count: int = 720) -> tuple[tuple[float, float], float]:
    """Normal angle across the ring (max, mean; degrees) and the normal spread at the pole."""
    s = np.linspace(*tube.mesh.s_range, count, endpoint=False)
    t_ring = tube.mesh.t_range[0] if end == "distal" else tube.mesh.t_range[1]
    r_ring, r_pole = (1.0, 0.0) if end == "distal" else (0.0, 1.0)
    a = tube.evaluate(s, np.full(count, t_ring), order=1)
    b = cap.evaluate(s, np.full(count, r_ring), order=1)
    na = _unit(np.cross(a.du, a.dv))
    nb = _unit(np.cross(b.du, b.dv))
    ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", na, nb), -1.0, 1.0)))
    eps = 1e-4
    near = cap.evaluate(s, np.full(count, abs(r_pole - eps)), order=1)
    npole = _unit(np.cross(near.du, near.dv))
    mean = _unit(npole.mean(axis=0, keepdims=True))[0]
    spread = np.degrees(np.arccos(np.clip(npole @ mean, -1.0, 1.0))).max()
    return (float(ang.max()), float(ang.mean())), float(spread)
