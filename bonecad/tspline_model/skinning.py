"""Global (s, t) parameterisation of the tibia and approximate skinning of the
three contour-curve sets into one T-spline (DESIGN.md step 5).

Parameter domain (all in mm, so the thin-plate fairness is near-isotropic):

- s, periodic, period 2 pi r_shaft (mean shaft radius): the angle about the
  axis of each region from lateral (s = 0) towards anterior, scaled to mm;
- t, clamped: the mean meridian arc length, from the distal apex ring
  (t = 0) through the distal region, along the shaft (t grows with height)
  and across the proximal region to the proximal apex ring.

Every curve point gets its (s, t): a half-plane curve at angle theta gives s,
its arc-length share gives t; a shaft section gives t from its height and s
from the angle of each point about the section centre. Curves of one region
have different knot vectors and are not made compatible: the T-spline is
fitted to all their points at once by least squares (approximate skinning,
cf. Yang et al. 2012, "Approximate T-spline surface skinning"), on one
T-mesh spanning the three regions, so the regions are bridged C2 by
construction. Near each apex ring only every other s-line reaches the ring:
the rows that would crowd there end in T-junctions (the paper's Fig. 8 edge
deletion against wrinkles), built into the T-mesh directly.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bonecad.contours.curves import ContourSet
from bonecad.errors import FitError
from bonecad.splines.tspline import TMesh, TSpline

from bonecad.splines.tspline.fit import solve_control_points

#: Samples per curve when a curve becomes skinning data.
_OPEN_SAMPLES = 60
_CLOSED_SAMPLES = 96


@dataclass(frozen=True)
class Parameterisation:
    """The tibia's parameter domain (mm).

    s_period : period of s; t_distal, t_proximal : t of the distal/shaft and
    shaft/proximal region boundaries; t_end : t of the proximal apex ring.
    z_distal, z_proximal : the region boundaries' heights (bone z, mm).
    local_axis : (2, 3) plateau centre, lowest proximal centroid (bone coordinates).
    """

    s_period: float
    t_distal: float
    t_proximal: float
    t_end: float
    z_distal: float
    z_proximal: float
    local_axis: np.ndarray

    def shaft_centre(self, level: np.ndarray) -> np.ndarray:
        """(n, 2) xy centre of the shaft section at heights ``level`` (as the contour curves use it)."""
        share = np.clip((np.asarray(level) - self.z_distal) / (self.z_proximal - self.z_distal), 0.0, 1.0)
        return share[:, None] * self.local_axis[1, :2][None, :]

    def to_dict(self) -> dict:
        return {
            "s_period_mm": self.s_period,
            "t_region_boundaries_mm": [self.t_distal, self.t_proximal],
            "t_end_mm": self.t_end,
        }


@dataclass(frozen=True)
class CurveData:
    """Skinning data: points of the contour curves with their (s, t)."""

    points: np.ndarray  # (n, 3) bone coordinates, mm
    s: np.ndarray
    t: np.ndarray
    region: np.ndarray  # (n,) 0 distal, 1 shaft, 2 proximal


def arc_samples(curve, count: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Points at equal arc-length shares along an open curve: (points, shares, length mm)."""
    u = np.linspace(0.0, 1.0, 801)
    p = curve(u)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    share = np.linspace(0.0, 1.0, count)
    uu = np.interp(share * cum[-1], cum, u)
    return curve(uu), share, float(cum[-1])


def parameterisation(contours: ContourSet) -> Parameterisation:
    """The parameter domain of a contour set (see the module docstring)."""
    frame = contours.frame
    z_d, z_p = frame.distal_boundary_mm, frame.proximal_boundary_mm
    if not contours.distal or not contours.proximal or not contours.shaft:
        raise FitError("T-spline skinning needs distal, shaft and proximal contour curves")
    loc = contours.local_axis_bone
    radii = []
    for c in contours.shaft:
        pts = c.curve(np.linspace(0.0, 1.0, 64, endpoint=False))
        centre = np.clip((c.level - z_d) / (z_p - z_d), 0, 1) * loc[1, :2]
        radii.append(np.linalg.norm(pts[:, :2] - centre, axis=1).mean())
    l_d = float(np.mean([arc_samples(c.curve, 8)[2] for c in contours.distal]))
    l_p = float(np.mean([arc_samples(c.curve, 8)[2] for c in contours.proximal]))
    period = 2 * np.pi * float(np.mean(radii))
    return Parameterisation(period, l_d, l_d + (z_p - z_d), l_d + (z_p - z_d) + l_p, z_d, z_p, loc.copy())


def curve_data(contours: ContourSet, par: Parameterisation) -> CurveData:
    """All contour-curve points with their (s, t) (see the module docstring)."""
    pts, ss, tt, reg = [], [], [], []
    for c in contours.distal:
        p, share, _ = arc_samples(c.curve, _OPEN_SAMPLES)  # share 0 at the apex hole
        pts.append(p)
        ss.append(np.full(len(p), (c.angle % 360.0) / 360.0 * par.s_period))
        tt.append(share * par.t_distal)
        reg.append(np.zeros(len(p), int))
    for c in contours.shaft:
        p = c.curve(np.linspace(0.0, 1.0, _CLOSED_SAMPLES, endpoint=False))
        centre = par.shaft_centre(np.full(len(p), c.level_mm))
        ang = np.mod(np.arctan2(p[:, 1] - centre[:, 1], p[:, 0] - centre[:, 0]), 2 * np.pi)
        pts.append(p)
        ss.append(ang / (2 * np.pi) * par.s_period)
        tt.append(np.full(len(p), par.t_distal + (c.level - par.z_distal)))
        reg.append(np.ones(len(p), int))
    for c in contours.proximal:
        p, share, _ = arc_samples(c.curve, _OPEN_SAMPLES)  # share 0 at the apex hole
        pts.append(p)
        ss.append(np.full(len(p), (c.angle % 360.0) / 360.0 * par.s_period))
        tt.append(par.t_end - share * (par.t_end - par.t_proximal))
        reg.append(np.full(len(p), 2))
    return CurveData(np.vstack(pts), np.concatenate(ss), np.concatenate(tt), np.concatenate(reg))


def initial_mesh(par: Parameterisation, *, s_intervals: int, t_spacing_mm: float, apex_rows: int) -> TMesh:
    """The starting T-mesh: uniform s-lines, t-lines about ``t_spacing_mm`` apart
    within each region (region boundaries are t-lines), and every other s-line
    ending ``apex_rows`` rows before each apex ring (T-junctions).
    """
    if s_intervals < 8 or s_intervals % 2:
        raise FitError(f"initial_s_intervals must be an even number >= 8, got {s_intervals}")
    s_knots = np.arange(s_intervals) * (par.s_period / s_intervals)
    bounds = [0.0, par.t_distal, par.t_proximal, par.t_end]
    t_knots = [0.0]
    for a, b in zip(bounds[:-1], bounds[1:]):
        n = max(2, int(np.ceil((b - a) / t_spacing_mm)))
        t_knots.extend(np.linspace(a, b, n + 1)[1:])
    mesh = TMesh.grid(s_knots, np.array(t_knots), s_period=par.s_period)
    if apex_rows <= 0:
        return mesh
    t_edges = mesh.t_edges.copy()
    t_n = mesh.shape[1]
    rows = 3 + apex_rows  # t-line index where the odd s-lines end (T-junctions)
    for i in range(1, s_intervals, 2):
        t_edges[i, :rows] = False
        t_edges[i, t_n - 1 - rows :] = False
    return mesh.with_edges(mesh.s_edges, t_edges)


def skin(contours: ContourSet, par: Parameterisation, mesh: TMesh, *,
         fairness: float) -> tuple[TSpline, CurveData, np.ndarray]:
    """Least-squares skinning of the three curve sets on one T-mesh.

    Returns (T-spline, the curve data, distance of each curve point to the surface at its parameters, mm).
    """
    data = curve_data(contours, par)
    blank = TSpline(mesh, np.zeros((len(mesh.anchors), 3)), np.ones(len(mesh.anchors)))
    ts = solve_control_points(blank, data.s, data.t, data.points, fairness=fairness)
    residual = np.linalg.norm(ts.evaluate(data.s, data.t).points - data.points, axis=1)
    return ts, data, residual


def turned_over_triangles(s: np.ndarray, t: np.ndarray, faces: np.ndarray, period: float) -> np.ndarray:
    """(f,) bool: the mesh triangles whose image in the (s, t) domain (mm; s periodic with ``period``) has
    the orientation opposite to the majority's: where the points' parameters cross.

    A least-squares fit to parameters that cross must turn its surface over there: the fitted elements
    fold (issue 45; docs/guides/femur-folds.md). Triangles squeezed to no area (a clamped apex ring) are
    not counted.
    """
    ds = s[faces[:, 1:]] - s[faces[:, :1]]
    ds = (ds + 0.5 * period) % period - 0.5 * period
    dt = t[faces[:, 1:]] - t[faces[:, :1]]
    area = ds[:, 0] * dt[:, 1] - ds[:, 1] * dt[:, 0]
    return area * np.sign(np.sum(area)) < 0
