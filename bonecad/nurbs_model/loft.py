"""The NURBS baseline's surfaces in numpy (bone coordinates): skinned ends, lofted shaft, ring caps.

Every surface is parametrised the same way, like one sphere: u runs round the
bone (periodic, 28 uniform poles, u = 0 lateral, counter-clockwise about +z),
v runs along the meridian from the distal apex towards the proximal apex, so
S_u x S_v points out of the bone on every face.

- **Ends** (DESIGN.md step 4): the region's 28 half-plane curves are made
  compatible (one knot vector, the average of theirs, each curve refitted to
  its raw section with it), then skinned round the bone by periodic cubic
  interpolation of the pole rows (NURBS Book 10.3; our own circulant solve, no
  double knot at the seam). Curve j is interpolated at the parameter where it
  meets the boundary shaft section, so u means the same on the end surface
  and on the shaft next to it.
- **Shaft**: its first and last sections are replaced by the end surfaces'
  boundary iso-curves (same 28-pole periodic space), then all sections are
  interpolated along the axis (clamped cubic, chord-length parameters), so
  the shaft meets both ends exactly: C0 (identical poles; the paper's joins),
  or with ``joins`` "G1" also tangent: the shaft's derivative across each end
  is the end surface's, scaled (cubic interpolation with end derivatives).
- **Ring caps**: ruled cones from the apex point on the axis to the apex ring
  iso-curve (the paper's ring of 28 lines through the apex); with "G1" joins
  a cubic cap instead, tangent to the end surface along the ring (its last
  pole row the ring, the one before it along the end surface's derivative)
  and flat at the apex (its second pole row in the plane across the axis).

OpenCascade's offset (BRepOffset_Analyse) refuses a seam whose faces are
tangent within 0.1 rad at some of its 23 samples and not at others
(BRepOffset_MixedConnectivity): the C0 joins of a bone, nearly tangent in
places, do exactly that; G1 joins are tangent everywhere.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bonecad.splines.curve import BSplineCurve, densified, fit_curve
from bonecad.contours.curves import ContourCurve, ContourSet
from bonecad.errors import FitError
from bonecad.splines.basis import design_matrix
from bonecad.splines.knots import periodic_knots
from bonecad.splines.project import project_to_curve
from bonecad.splines.surface import BSplineSurface, end_derivative, interpolate_clamped, interpolate_periodic

JOINS: tuple[str, ...] = ("G1", "C0")


@dataclass(frozen=True)
class RefitReport:
    """How far the compatible (common-knot) curves of one region lie from their raw sections (mm)."""

    region: str
    max_deviation_mm: float  # worst curve
    rms_deviation_mm: float  # mean of the curves' RMS
    original_max_deviation_mm: float  # worst curve before the refit (own knots)
    dropped_points: int  # raw points the original fit had bridged (artefact peaks)

    def to_dict(self) -> dict:
        return {k: (round(v, 5) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


def common_knots(curves: list[BSplineCurve]) -> np.ndarray:
    """The average of the curves' clamped knot vectors (all of one pole count and degree)."""
    counts = {(c.count, c.degree, c.periodic) for c in curves}
    if len(counts) != 1 or next(iter(counts))[2]:
        raise FitError(f"curves to make compatible must be open and share pole count and degree, got {sorted(counts)}")
    return np.mean([c.knots for c in curves], axis=0)


def refit_to_knots(
    contour: ContourCurve,
    knots: np.ndarray,
    *,
    corrections: int = 4,
    fairness: float = 1e-4,
    bridged_mm: float = 0.5,
) -> tuple[BSplineCurve, float, float, int]:
    """Least-squares refit of a contour's raw section with the given clamped knots, ends interpolated.

    Raw points farther than max(``bridged_mm``, 2 x its max deviation) from the
    original curve are the artefact peaks its fit bridged: they stay out. The
    fit (:func:`bonecad.splines.curve.fit_curve`) alternates point-distance solves
    with parameter correction, then takes tangent-distance steps, kept if they
    help. Returns (curve, max deviation, RMS deviation, points left out).
    """
    original = contour.curve
    points = densified(np.asarray(contour.raw_points, dtype=np.float64), 4 * original.count, closed=False)
    u = project_to_curve(original, points)
    u[0], u[-1] = 0.0, 1.0
    keep = np.linalg.norm(original(u) - points, axis=1) <= max(bridged_mm, 2.0 * contour.max_deviation_mm)
    keep[[0, -1]] = True
    fit = fit_curve(points[keep], knots=knots, params=u[keep], periodic=False, degree=original.degree,
                    corrections=corrections, tangent_pin_weight=1e8, outlier_mm=None, fairness=fairness)
    return fit.curve, fit.max_deviation_mm, fit.rms_deviation_mm, int((~keep).sum())


def compatible_curves(contours: tuple[ContourCurve, ...], region: str) -> tuple[list[BSplineCurve], RefitReport]:
    """The region's curves refitted to their average knot vector, and how well they still fit."""
    if len(contours) < 4:
        raise FitError(f"the {region} region needs at least 4 curves to skin, got {len(contours)}")
    knots = common_knots([c.curve for c in contours])
    fits = [refit_to_knots(c, knots) for c in contours]
    report = RefitReport(
        region=region,
        max_deviation_mm=max(f[1] for f in fits),
        rms_deviation_mm=float(np.mean([f[2] for f in fits])),
        original_max_deviation_mm=max(c.max_deviation_mm for c in contours),
        dropped_points=sum(f[3] for f in fits),
    )
    return [f[0] for f in fits], report


def _unwrapped(angles: np.ndarray) -> np.ndarray:
    """Angles (radians) made to increase from the first, once round (raises if they do not go round in order)."""
    steps = np.mod(np.diff(angles), 2 * np.pi)
    total = steps.sum() + np.mod(angles[0] - angles[-1], 2 * np.pi)
    if np.any(steps <= 0) or abs(total - 2 * np.pi) > 1e-6:
        raise FitError("the end curves do not go once round the bone in order (lateral -> anterior)")
    return angles[0] + np.concatenate([[0.0], np.cumsum(steps)])


@dataclass(frozen=True)
class AngleMap:
    """Which u each direction round the shaft gets: curve j of an end region sits at u = j / n.

    distal_deg, proximal_deg : (n,) polar angles (about the shaft centre line) where
        the distal and proximal curves meet their boundary planes; levels between
        blend them linearly, so every shaft section is parametrised like its neighbours.
    """

    distal: np.ndarray
    proximal: np.ndarray
    distal_z: float
    proximal_z: float
    proximal_centre_xy: np.ndarray

    def centre(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        share = np.clip((np.asarray(z) - self.distal_z) / (self.proximal_z - self.distal_z), 0.0, 1.0)
        return share[..., None] * self.proximal_centre_xy, share

    def parameters(self, points: np.ndarray) -> np.ndarray:
        """u in [0, 1) of section points (m, 3) at their polar angle about the centre line."""
        centre, share = self.centre(points[:, 2])
        rel = points[:, :2] - centre
        theta = np.arctan2(rel[:, 1], rel[:, 0])
        mean_share = float(np.mean(share))
        knots = (1.0 - mean_share) * self.distal + mean_share * self.proximal
        n = len(knots)
        theta = knots[0] + np.mod(theta - knots[0], 2 * np.pi)
        return np.mod(np.interp(theta, np.append(knots, knots[0] + 2 * np.pi), np.arange(n + 1) / n), 1.0)


def angle_map(contours: ContourSet, distal_ends: np.ndarray, proximal_ends: np.ndarray) -> AngleMap:
    """The angle -> u correspondence fixed by where the end curves meet the boundary planes."""
    frame = contours.frame
    centre = contours.local_axis_bone[1, :2]
    distal = _unwrapped(np.arctan2(distal_ends[:, 1], distal_ends[:, 0]))
    rel = proximal_ends[:, :2] - centre
    proximal = _unwrapped(np.arctan2(rel[:, 1], rel[:, 0]))
    # both sequences start near 0 (lateral): keep them on the same turn
    proximal += 2 * np.pi * np.round((distal[0] - proximal[0]) / (2 * np.pi))
    return AngleMap(distal, proximal, frame.distal_boundary_mm, frame.proximal_boundary_mm, centre)


def refit_section(
    contour: ContourCurve, mapping: AngleMap, *, fairness: float = 1e-4
) -> tuple[BSplineCurve, float, float]:
    """A shaft section refitted with the parameters of ``mapping`` (no parameter correction, which
    would drift back to arc length). Returns the curve and its largest and RMS distance from the
    raw section (mm)."""
    original = contour.curve
    count = original.count
    points = densified(np.asarray(contour.raw_points, dtype=np.float64), 4 * count, closed=True)
    u_orig = project_to_curve(original, points)
    keep = np.linalg.norm(original(u_orig) - points, axis=1) <= max(0.5, 2.0 * contour.max_deviation_mm)
    points = points[keep]
    # tangent-distance steps: errors across the curve count, sliding along it barely
    curve = fit_curve(points, knots=periodic_knots(count), params=mapping.parameters(points), periodic=True,
                      correct_parameters=False, tangent_steps=2, pin_ends=False, outlier_mm=None,
                      fairness=fairness).curve
    foot = project_to_curve(curve, points)  # not from u: Newton from the mapped parameters can jump
    distance = np.linalg.norm(curve(foot) - points, axis=1)
    return curve, float(distance.max()), float(np.sqrt(np.mean(distance**2)))


def iso_u_curve(surface: BSplineSurface, v: float) -> BSplineCurve:
    """The curve u -> S(u, v) of a polynomial surface (exact: its poles are the v-blend of the pole rows)."""
    if surface.rational:
        raise ValueError("iso_u_curve: the iso-curve of a rational surface is rational; BSplineCurve is not")
    bv = design_matrix(np.array([float(v)]), surface.knots_v, surface.degree_v, surface.periodic_v,
                       surface.shape[1]).toarray()[0]
    return BSplineCurve(np.einsum("abk,b->ak", surface.poles, bv), surface.knots_u, surface.degree_u,
                        surface.periodic_u)


def skin_end(curves: list[BSplineCurve], region: str) -> BSplineSurface:
    """Periodic-in-u skin through the compatible curves, curve j at u = j / n (v as the curves run:
    apex -> boundary). Uniform parameters keep the circulant system well posed: interpolating at
    the curves' arc-length positions instead leaves knot spans without a parameter and the skin
    swings out by centimetres between curves."""
    rows = np.stack([c.control_points for c in curves])  # (28, count, 3)
    poles = interpolate_periodic(rows)
    return BSplineSurface(poles, periodic_knots(len(curves)), curves[0].knots, 3, curves[0].degree,
                          periodic_u=True, region=region)


def loft_shaft(first: BSplineCurve, middle: list[BSplineCurve], last: BSplineCurve, *,
               end_tangents: tuple[np.ndarray, np.ndarray] | None = None) -> BSplineSurface:
    """Clamped cubic interpolation along the axis through the sections (all one periodic space).

    end_tangents : pole rows (28, 3) of the directions the shaft must leave its first and
        enter its last section along (the end surfaces' cross derivatives, any scale);
        each is scaled so that its mean component along the shaft's chord equals the
        chord length (the shaft's own speed), which keeps the joins G1 and the
        parameterisation even.
    """
    sections = [first, *middle, last]
    counts = {(c.count, c.periodic) for c in sections}
    if len(counts) != 1 or not next(iter(counts))[1]:
        raise FitError(f"shaft sections must all be periodic with one pole count, got {sorted(counts)}")
    rows = np.stack([c.control_points for c in sections])  # (N, 28, 3)
    centres = rows.mean(axis=1)
    chord = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(centres, axis=0), axis=1))])
    if chord[-1] <= 0 or np.any(np.diff(chord) <= 0):
        raise FitError("shaft sections do not advance along the axis")
    derivatives = None
    if end_tangents is not None:
        along = (centres[-1] - centres[0]) / np.linalg.norm(centres[-1] - centres[0])
        derivatives = tuple(t * chord[-1] / _mean_positive(t @ along, "shaft end tangent") for t in end_tangents)
    poles, knots = interpolate_clamped(rows, chord / chord[-1], end_derivatives=derivatives)
    return BSplineSurface(poles.transpose(1, 0, 2), first.knots, knots, 3, 3, periodic_u=True, region="shaft")


def ring_cap(ring: BSplineCurve, apex: np.ndarray, region: str, *, apex_first: bool) -> BSplineSurface:
    """Ruled cone (degree 1 in v) between the apex point and the ring curve."""
    tip = np.broadcast_to(np.asarray(apex, dtype=np.float64), ring.control_points.shape)
    rows = [tip, ring.control_points] if apex_first else [ring.control_points, tip]
    return BSplineSurface(np.stack(rows, axis=1), ring.knots, np.array([0.0, 0.0, 1.0, 1.0]), 3, 1,
                          periodic_u=True, region=region)


def _mean_positive(values: np.ndarray, what: str) -> float:
    mean = float(np.mean(values))
    if mean <= 0:
        raise FitError(f"the {what} points backwards (mean component {mean:.3g})")
    return mean


def tangent_ring_cap(ring: BSplineCurve, outward: np.ndarray, apex: np.ndarray, axis: np.ndarray, region: str, *,
                     apex_first: bool) -> BSplineSurface:
    """Cubic cap (in v) from the apex to the ring, tangent along the ring to the surface it closes.

    outward : pole rows (28, 3) of the end surface's derivative at the ring, pointing away
    from the apex (any scale). Pole rows from the apex: the apex; a third of the way to the
    ring in the plane across ``axis`` (a flat pole); the ring moved back along ``outward`` by a
    third of the ring's mean radius; the ring.
    """
    ring_poles = ring.control_points
    axis = axis / np.linalg.norm(axis)
    radial = ring_poles - apex
    radial -= np.outer(radial @ axis, axis)
    radius = float(np.mean(np.linalg.norm(radial, axis=1)))
    speed = float(np.mean(np.linalg.norm(outward, axis=1)))
    rows = [np.broadcast_to(apex, ring_poles.shape), apex + radial / 3.0,
            ring_poles - outward * (radius / 3.0 / speed), ring_poles]
    if not apex_first:
        rows = rows[::-1]
    return BSplineSurface(np.stack(rows, axis=1), ring.knots, np.array([0.0] * 4 + [1.0] * 4), 3, 3,
                          periodic_u=True, region=region)


def apex_on_axis(ring: BSplineCurve, point: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """The axis point at the ring's mean height along the axis (a cone as flat as the ring allows)."""
    direction = direction / np.linalg.norm(direction)
    samples = ring(np.linspace(0.0, 1.0, 112, endpoint=False))
    return point + float(np.mean((samples - point) @ direction)) * direction


@dataclass(frozen=True)
class BoneSurfaces:
    """The five regions' surfaces in bone coordinates, and the facts checked while building them."""

    distal: BSplineSurface
    shaft: BSplineSurface
    proximal: BSplineSurface
    distal_ring: BSplineCurve  # apex ring iso-curves (bone mm)
    proximal_ring: BSplineCurve
    distal_apex: np.ndarray  # (3,) apex points on the axes (bone mm)
    proximal_apex: np.ndarray
    distal_outward: np.ndarray  # (28, 3) end surfaces' derivative rows at the apex rings, away from the apex
    proximal_outward: np.ndarray
    proximal_axis: np.ndarray  # (3,) unit, from the proximal apex hole out of the bone
    refits: tuple[RefitReport, ...]  # distal, shaft, proximal
    boundary_shift_mm: tuple[float, float]  # how far the end iso-curves lie from the shaft's own end sections


def _curve_distance(a: BSplineCurve, b: BSplineCurve, samples: int = 400) -> float:
    """Largest distance from samples of ``a`` to ``b`` (foot points by projection)."""
    pts = a(np.linspace(0.0, 1.0, samples, endpoint=False))
    u = project_to_curve(b, pts)
    return float(np.linalg.norm(b(u) - pts, axis=1).max())


def _v_derivative(surface: BSplineSurface, end: int) -> np.ndarray:
    """Pole rows (nu, 3) of dS/dv along the iso-curve v = 0 (``end`` 0) or 1 of a polynomial surface."""
    return end_derivative(surface.poles.transpose(1, 0, 2), surface.knots_v, surface.degree_v, end)


def bone_surfaces(contours: ContourSet, joins: str = "G1") -> BoneSurfaces:
    """Skin the ends, loft the shaft between their boundary iso-curves (bone coordinates), C0 or G1
    (``joins``) to them."""
    if joins not in JOINS:
        raise ValueError(f"joins must be one of {JOINS}, got {joins!r}")
    if len(contours.shaft) < 2:
        raise FitError(f"the shaft needs at least 2 sections, got {len(contours.shaft)}")
    distal_curves, distal_report = compatible_curves(contours.distal, "distal")
    proximal_curves, proximal_report = compatible_curves(contours.proximal, "proximal")
    distal = skin_end(distal_curves, "distal")
    # the proximal curves run from the apex down: reverse v so it runs up the bone like the others
    proximal = skin_end(proximal_curves, "proximal").reversed_v()

    mapping = angle_map(
        contours,
        np.stack([c.control_points[-1] for c in distal_curves]),
        np.stack([c.control_points[-1] for c in proximal_curves]),
    )
    middle = [refit_section(c, mapping) for c in contours.shaft[1:-1]]
    distal_boundary, proximal_boundary = iso_u_curve(distal, 1.0), iso_u_curve(proximal, 0.0)
    tangents = (_v_derivative(distal, 1), _v_derivative(proximal, 0)) if joins == "G1" else None
    shaft = loft_shaft(distal_boundary, [m[0] for m in middle], proximal_boundary, end_tangents=tangents)
    shaft_report = RefitReport(
        region="shaft",
        max_deviation_mm=max([m[1] for m in middle], default=0.0),
        rms_deviation_mm=float(np.mean([m[2] for m in middle])) if middle else 0.0,
        original_max_deviation_mm=max(c.max_deviation_mm for c in contours.shaft),
        dropped_points=0,
    )

    distal_ring, proximal_ring = iso_u_curve(distal, 0.0), iso_u_curve(proximal, 1.0)
    local = contours.local_axis_bone
    return BoneSurfaces(
        distal=distal,
        shaft=shaft,
        proximal=proximal,
        distal_ring=distal_ring,
        proximal_ring=proximal_ring,
        distal_apex=apex_on_axis(distal_ring, np.zeros(3), np.array([0.0, 0.0, 1.0])),
        proximal_apex=apex_on_axis(proximal_ring, local[0], local[0] - local[1]),
        distal_outward=_v_derivative(distal, 0),
        proximal_outward=-_v_derivative(proximal, 1),
        proximal_axis=(local[0] - local[1]) / np.linalg.norm(local[0] - local[1]),
        refits=(distal_report, shaft_report, proximal_report),
        boundary_shift_mm=(
            _curve_distance(distal_boundary, contours.shaft[0].curve),
            _curve_distance(proximal_boundary, contours.shaft[-1].curve),
        ),
    )
