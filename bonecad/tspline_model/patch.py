"""A plate's footprint: one region of the T-spline tube as one untrimmed B-spline surface, exact.

The region is given in the anatomical frame: a height range along the
mechanical axis (mm above the plafond centre) and an angle range round it
(degrees from lateral towards anterior: 90 anterior, 180 medial, 270
posterior, the contour curves' convention, the same for left and right
tibias). The tube's parameters follow those directions (s round the bone from
lateral, t up the bone), not exactly, so the footprint is the parameter
rectangle whose edges lie, on average, at the requested heights and angles
(two alternating passes); the heights and angles it actually spans are
reported. The surface is :func:`bonecad.splines.tspline.tensor.region_patch` of
that rectangle: the T-spline itself, to rounding.

::

    footprint = footprint_patch(tube_bone, PatchRegion("anteromedial_distal_tibia", (8, 80), (95, 175)))
    footprint.surface        # BSplineSurface, bone coordinates (mm)
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bonecad.errors import InputError
from bonecad.splines.surface import BSplineSurface
from bonecad.splines.tspline import TSpline
from bonecad.splines.tspline.tensor import region_patch

#: Samples per parameter direction when matching the rectangle to the region.
_SAMPLES = 181


@dataclass(frozen=True)
class PatchRegion:
    """A region of the bone surface: name, heights (mm above the plafond centre) and angles (degrees from
    lateral towards anterior; the range may pass 360, e.g. (330, 390))."""

    name: str
    height_mm: tuple[float, float]
    angle_deg: tuple[float, float]

    def __post_init__(self) -> None:
        (h0, h1), (a0, a1) = self.height_mm, self.angle_deg
        if not h1 > h0:
            raise InputError(f"region {self.name!r}: the height range {self.height_mm} mm must increase")
        if not 0 < a1 - a0 < 360:
            raise InputError(f"region {self.name!r}: the angle range {self.angle_deg} deg must increase by "
                             "less than a turn")


@dataclass(frozen=True)
class Footprint:
    """The region's surface (bone coordinates, mm), its tube parameters, the heights (mm) and angles (deg)
    its points span, and how far it lies from the T-spline at check samples (mm)."""

    region: PatchRegion
    surface: BSplineSurface
    s_range: tuple[float, float]
    t_range: tuple[float, float]
    height_span_mm: tuple[float, float]
    angle_span_deg: tuple[float, float]
    tspline_deviation_mm: float

    def summary(self) -> dict:
        r = self.region
        return {
            "region": {"name": r.name, "height_mm": list(r.height_mm), "angle_deg": list(r.angle_deg)},
            "parameters": {"s": [round(v, 6) for v in self.s_range], "t": [round(v, 6) for v in self.t_range]},
            "spans": {"height_mm": [round(v, 3) for v in self.height_span_mm],
                      "angle_deg": [round(v, 3) for v in self.angle_span_deg]},
            "poles": list(self.surface.shape),
            "deviation_from_tspline_mm": self.tspline_deviation_mm,
        }


def _angles_deg(points: np.ndarray, start: float) -> np.ndarray:
    """Polar angles (deg) about the bone's z axis, unwrapped into [start - 180, start + 180)."""
    angle = np.degrees(np.arctan2(points[..., 1], points[..., 0]))
    return start + np.mod(angle - start + 180.0, 360.0) - 180.0


def _crossing(values: np.ndarray, params: np.ndarray, target: float, what: str) -> float:
    """The parameter where ``values`` (increasing overall along ``params``) first reach ``target``."""
    above = np.flatnonzero(values >= target)
    if len(above) == 0 or values[0] > target:
        raise InputError(f"the {what} {target:g} lies outside the bone's surface ({values.min():.1f} to "
                         f"{values.max():.1f})")
    k = above[0]
    if k == 0:
        return float(params[0])
    f = (target - values[k - 1]) / (values[k] - values[k - 1])
    return float(params[k - 1] + f * (params[k] - params[k - 1]))


def footprint_patch(tube: TSpline, region: PatchRegion) -> Footprint:
    """The parameter rectangle of ``tube`` (bone coordinates) matching ``region``, as one exact surface."""
    mesh = tube.mesh
    period = mesh.s_period
    if period is None:
        raise InputError("footprints are cut from a tube that goes round the bone (periodic s)")
    s_lo, _ = mesh.s_range
    t_lo, t_hi = mesh.t_range
    (h0, h1), (a0, a1) = region.height_mm, region.angle_deg
    middle = 0.5 * (a0 + a1)
    # start: s in proportion to the angle (as the skinning parameterised it), the whole t range
    s_range = (s_lo + a0 / 360.0 * period, s_lo + a1 / 360.0 * period)
    t_range = (t_lo, t_hi)
    t_grid = np.linspace(t_lo, t_hi, _SAMPLES)
    for _ in range(2):
        s_grid = np.linspace(*s_range, 9)
        ss, tt = np.meshgrid(s_grid, t_grid, indexing="ij")
        heights = tube.evaluate(np.mod(ss.ravel() - s_lo, period) + s_lo, tt.ravel()).points[:, 2]
        mean_height = heights.reshape(ss.shape).mean(axis=0)
        t_range = (_crossing(mean_height, t_grid, h0, "height (mm)"), _crossing(mean_height, t_grid, h1, "height (mm)"))
        s_grid = np.linspace(s_range[0] - 0.25 * period, s_range[1] + 0.25 * period, _SAMPLES)
        ss, tt = np.meshgrid(s_grid, np.linspace(*t_range, 9), indexing="ij")
        points = tube.evaluate(np.mod(ss.ravel() - s_lo, period) + s_lo, tt.ravel()).points
        mean_angle = _angles_deg(points, middle).reshape(ss.shape).mean(axis=1)
        s_range = (_crossing(mean_angle, s_grid, a0, "angle (deg)"), _crossing(mean_angle, s_grid, a1, "angle (deg)"))
    surface = region_patch(tube, s_range, t_range, region=region.name)
    u = np.linspace(*s_range, 41)
    v = np.linspace(*t_range, 41)
    uu, vv = (a.ravel() for a in np.meshgrid(u, v, indexing="ij"))
    points = surface.evaluate(uu, vv).points
    gap = np.linalg.norm(points - tube.evaluate(np.mod(uu - s_lo, period) + s_lo, vv).points, axis=1).max()
    angles = _angles_deg(points, middle)
    return Footprint(region, surface, s_range, t_range, (float(points[:, 2].min()), float(points[:, 2].max())),
                     (float(angles.min()), float(angles.max())), float(gap))


def mesh_deviation(surface: BSplineSurface, vertices: np.ndarray, faces: np.ndarray, samples: int) -> dict:
    """Distances (mm) from a ``samples`` x ``samples`` grid of the surface (parameters) to the mesh (same
    coordinates): RMS, largest, and the shares within 0.1 / 0.25 / 0.5 / 1 mm."""
    from bonecad.mesh.closest import TriangleLocator

    u0, u1, v0, v1 = surface.bounds
    uu, vv = (a.ravel() for a in np.meshgrid(np.linspace(u0, u1, samples), np.linspace(v0, v1, samples)))
    distance = TriangleLocator(vertices, faces).query(surface.evaluate(uu, vv).points).distance
    return {
        "samples": int(distance.size),
        "rms_mm": round(float(np.sqrt(np.mean(distance**2))), 5),
        "max_mm": round(float(distance.max()), 5),
        "share_within_mm": {f"{b:g}": round(float(np.mean(distance <= b)), 5) for b in (0.1, 0.25, 0.5, 1.0)},
    }
