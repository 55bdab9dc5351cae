"""A fixation plate planned on a footprint of the T-spline: outline, seat, holes, screws and fit (bone coordinates).

The plate lies on the footprint of :mod:`bonecad.tspline_model.patch` (one
exact B-spline surface, parameters u = s round the bone and v = t up it). Its
centre line is the footprint's middle u line; lengths along it (y) and across
it along the u lines (x) are arc lengths on the surface (developed
coordinates, mm), so the outline, a rounded rectangle of the given width
(tapered from the distal to the proximal end) and end radius, is drawn in mm
and mapped to (u, v): a closed curve in the surface's parameters, which the
OpenCascade side makes the trimmed face of the plate's underside.

The underside is the footprint offset along its outward normal by the gap
plus the seat: the largest depth by which the offset surface would lie inside
the bone mesh at the fit samples (the T-spline is a fit, within a few tenths
of a mm of the mesh), so that the plate touches the bone at the gap and does
not cut into it. The fit samples (a grid of ``fit_sample_mm`` inside the
outline) give the distances from the underside to the mesh.

Each hole sits on the centre line; its screw runs from the plate's top along
the inward normal (tilted by the per-hole angles), and its length is where
its axis last leaves the bone (the far cortex: bicortical), rounded up to the
stock step. Checks: the axis stays inside the bone between its entry and that
exit, the screws miss each other by a screw diameter (segment distances), and
no exit lies within the joint margin of an articular end (heights of the
apices where the frame's axis leaves the bone). A screw whose axis misses the
bone, or is longer than the maximum, cannot be placed: InputError naming it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bonecad.errors import InputError
from bonecad.mesh.closest import TriangleLocator
from bonecad.mesh.rays import ray_hits
from bonecad.settings import PlateSettings
from bonecad.splines.basis import design_matrix
from bonecad.splines.lsq import least_squares
from bonecad.splines.surface import BSplineSurface
from bonecad.tspline_model.patch import Footprint, PatchRegion

#: Stations along the centre line and samples across it for the developed coordinates.
_STATIONS = 241
_ACROSS = 241
#: Spacing (mm) of the outline's points in developed coordinates.
_OUTLINE_STEP_MM = 1.5
#: Plate material kept between the outline and the footprint's side edges (mm).
_SIDE_MARGIN_MM = 0.5
#: A screw that leaves the bone for more than this between its cortices is flagged (mm).
_OUTSIDE_TOLERANCE_MM = 0.5


@dataclass(frozen=True)
class Screw:
    """One screw (bone coordinates, mm): its hole (1-based), the hole's point on the underside and the
    screw's head point on the plate's top, its unit direction, where it enters the bone and leaves the far
    cortex, its length from the head point to that exit, the stock length, how far its axis runs outside
    the bone between entry and exit, the clearance to the nearest other screw (surface to surface, mm) and
    the checks it fails (empty: none)."""

    hole: int
    underside: np.ndarray
    head: np.ndarray
    direction: np.ndarray
    entry: np.ndarray
    exit: np.ndarray
    length_mm: float
    stock_mm: float
    outside_mm: float
    clearance_mm: float
    warnings: tuple[str, ...]

    @property
    def tip(self) -> np.ndarray:
        return self.head + self.stock_mm * self.direction


@dataclass(frozen=True)
class PlatePlan:
    """The planned plate (bone coordinates, mm): the footprint, the surface under the plate (the footprint,
    or :func:`smoothed`, same parameters; the underside is its offset) and its knot spacing (mm; None: the
    footprint itself), the outline and centre line in those
    parameters ((n, 2) u, v), the underside's offset (gap + seat) and the outward sign of S_u x S_v, the
    developed length, the holes' parameters, the screws, and the fit: signed distances (mm) from the
    underside's samples to the mesh (< 0: inside the bone)."""

    footprint: Footprint
    settings: PlateSettings
    underside: BSplineSurface
    smoothing_mm: float | None
    outline_uv: np.ndarray
    centre_uv: np.ndarray
    seat_mm: float
    outward: float
    length_mm: float
    hole_uv: np.ndarray
    hole_y: np.ndarray
    screws: tuple[Screw, ...]
    fit_points: np.ndarray
    fit_distance_mm: np.ndarray
    joint_heights_mm: tuple[float, float]

    @property
    def offset_mm(self) -> float:
        """The underside's distance from the footprint along its outward normal (mm)."""
        return self.settings.gap_mm + self.seat_mm

    def centre_points(self, offset_mm: float = 0.0) -> np.ndarray:
        """(n, 3) the centre line, offset along the outward normal by ``offset_mm`` (mm)."""
        return _offset_points(self.underside, self.centre_uv, offset_mm, self.outward)

    def fit_summary(self) -> dict:
        """Shares of the samples within gap + 0.5 / 1 / 2 mm, the largest distance and penetration (mm)."""
        d, gap = self.fit_distance_mm, self.settings.gap_mm
        return {
            "samples": int(d.size),
            "gap_mm": gap,
            "seat_mm": round(self.seat_mm, 4),
            "share_within_gap_plus_mm": {f"{b:g}": round(float(np.mean(d <= gap + b)), 5) for b in (0.5, 1.0, 2.0)},
            "share_within_mm": {f"{b:g}": round(float(np.mean(np.abs(d) <= b)), 5) for b in (0.5, 1.0, 2.0)},
            "mean_mm": round(float(d.mean()), 4),
            "largest_gap_mm": round(float(d.max()), 4),
            "largest_penetration_mm": round(float(max(0.0, -d.min())), 4),
        }


def _frames(surface: BSplineSurface, uv: np.ndarray, outward: float):
    """Points, unit outward normals, unit u and v tangents of ``surface`` at ``uv`` (n, 2)."""
    sample = surface.evaluate(uv[:, 0], uv[:, 1], order=1)
    normal = outward * np.cross(sample.du, sample.dv)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    du = sample.du / np.linalg.norm(sample.du, axis=1, keepdims=True)
    dv = sample.dv / np.linalg.norm(sample.dv, axis=1, keepdims=True)
    return sample.points, normal, du, dv


def _offset_points(surface: BSplineSurface, uv: np.ndarray, offset_mm: float, outward: float) -> np.ndarray:
    points, normal, _, _ = _frames(surface, uv, outward)
    return points + offset_mm * normal


def outward_sign(surface: BSplineSurface) -> float:
    """+1 when S_u x S_v points out of the bone (away from its z axis, bone coordinates), else -1."""
    u0, u1, v0, v1 = surface.bounds
    uu, vv = (a.ravel() for a in np.meshgrid(np.linspace(u0, u1, 9), np.linspace(v0, v1, 9)))
    sample = surface.evaluate(uu, vv, order=1)
    radial = sample.points * np.array([1.0, 1.0, 0.0])
    return 1.0 if np.sum(np.einsum("ij,ij->i", np.cross(sample.du, sample.dv), radial)) > 0 else -1.0


class Developed:
    """Developed coordinates on a footprint: y the arc length up its middle u line from its v start, x the
    arc length along the u line at that height from the face's middle there (half way along the line,
    towards higher u), mm: the centre line x = 0 halves the face at every height."""

    def __init__(self, surface: BSplineSurface):
        u0, u1, v0, v1 = surface.bounds
        self.v = np.linspace(v0, v1, _STATIONS)
        self.u = np.linspace(u0, u1, _ACROSS)
        self.u_mid = 0.5 * (u0 + u1)
        centre = surface.evaluate(np.full_like(self.v, self.u_mid), self.v).points
        self.y = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(centre, axis=0), axis=1))])
        uu, vv = np.meshgrid(self.u, self.v)  # rows: stations
        grid = surface.evaluate(uu.ravel(), vv.ravel()).points.reshape(_STATIONS, _ACROSS, 3)
        across = np.concatenate([np.zeros((_STATIONS, 1)),
                                 np.cumsum(np.linalg.norm(np.diff(grid, axis=1), axis=2), axis=1)], axis=1)
        self.x = across - 0.5 * across[:, -1:]  # (stations, across) arc length from the face's middle
        self.heights = centre[:, 2]

    @property
    def length_mm(self) -> float:
        return float(self.y[-1])

    def half_widths(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The face's extent (mm) below and above the middle (towards lower and higher u) at lengths ``y``."""
        return np.interp(y, self.y, -self.x[:, 0]), np.interp(y, self.y, self.x[:, -1])

    def to_uv(self, xy: np.ndarray) -> np.ndarray:
        """(n, 2) developed (x, y) mm -> (n, 2) surface parameters (u, v)."""
        x, y = xy[:, 0], xy[:, 1]
        v = np.interp(y, self.y, self.v)
        k = np.clip(np.searchsorted(self.y, y) - 1, 0, _STATIONS - 2)
        f = np.clip((y - self.y[k]) / (self.y[k + 1] - self.y[k]), 0.0, 1.0)
        u_lo = np.array([np.interp(xi, self.x[ki], self.u) for xi, ki in zip(x, k)])
        u_hi = np.array([np.interp(xi, self.x[ki + 1], self.u) for xi, ki in zip(x, k)])
        return np.column_stack([(1 - f) * u_lo + f * u_hi, v])


def _half_width(settings: PlateSettings, y: np.ndarray, y0: float, y1: float) -> np.ndarray:
    w0, w1 = settings.width_mm
    return 0.5 * (w0 + (w1 - w0) * np.clip((y - y0) / (y1 - y0), 0.0, 1.0))


def outline_xy(settings: PlateSettings, y0: float, y1: float) -> np.ndarray:
    """The outline (developed mm), counter-clockwise from the middle of the distal end, not closed: straight
    (tapered) sides and rounded corners of radius ``end_radius_mm``."""
    r = settings.end_radius_mm
    hw0, hw1 = (float(_half_width(settings, np.array(y), y0, y1)) for y in (y0, y1))
    # corner centres and the quarter arcs, counter-clockwise
    corners = [((hw0 - r, y0 + r), -90.0), ((hw1 - r, y1 - r), 0.0), ((-(hw1 - r), y1 - r), 90.0),
               ((-(hw0 - r), y0 + r), 180.0)]
    path = [np.array([[0.0, y0]])]
    for (cx, cy), start in corners:
        a = np.radians(np.linspace(start, start + 90.0, 13))
        path.append(np.column_stack([cx + r * np.cos(a), cy + r * np.sin(a)]))
    path.append(np.array([[0.0, y0]]))
    polygon = np.concatenate(path)
    # resample at even spacing along the polygon
    seg = np.linalg.norm(np.diff(polygon, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    polygon = polygon[keep]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(polygon, axis=0), axis=1))])
    n = max(24, int(np.ceil(s[-1] / _OUTLINE_STEP_MM)))
    t = np.linspace(0.0, s[-1], n, endpoint=False)
    return np.column_stack([np.interp(t, s, polygon[:, 0]), np.interp(t, s, polygon[:, 1])])


def inside_outline(settings: PlateSettings, xy: np.ndarray, y0: float, y1: float) -> np.ndarray:
    """(n,) bool: developed points inside the outline."""
    x, y = np.abs(xy[:, 0]), xy[:, 1]
    r = settings.end_radius_mm
    hw = _half_width(settings, y, y0, y1)
    inside = (y >= y0) & (y <= y1) & (x <= hw)
    for end_y, centre_y in ((y0, y0 + r), (y1, y1 - r)):
        hw_end = float(_half_width(settings, np.array(end_y), y0, y1))
        zone = ((y < centre_y) if end_y == y0 else (y > centre_y)) & (x > hw_end - r)  # the corner's square
        inside &= ~zone | ((x - (hw_end - r)) ** 2 + (y - centre_y) ** 2 <= r * r)
    return inside


def hole_positions(settings: PlateSettings, y0: float, y1: float) -> np.ndarray:
    """The holes' lengths along the centre line (mm): ``holes`` evenly, or as many as the spacing allows,
    centred; the outer ones ``hole_end_distance_mm`` from the ends."""
    first, last = y0 + settings.hole_end_distance_mm, y1 - settings.hole_end_distance_mm
    if last < first:
        raise InputError(f"the plate is {y1 - y0:.1f} mm long: too short for holes {settings.hole_end_distance_mm} "
                         "mm from each end")
    count = settings.holes or int(np.floor((last - first) / settings.hole_spacing_mm + 1e-9)) + 1
    if count == 1:
        return np.array([0.5 * (first + last)])
    if settings.holes == 0:
        span = (count - 1) * settings.hole_spacing_mm
        first, last = 0.5 * (first + last - span), 0.5 * (first + last + span)
    return np.linspace(first, last, count)


def signed_distances(locator: TriangleLocator, points: np.ndarray) -> np.ndarray:
    """(n,) mm: distances of ``points`` from the mesh, negative inside it (the side of the nearest triangle's
    outward normal at the closest point)."""
    found = locator.query(points)
    tri = locator.vertices[locator.triangles[found.triangle]]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    side = np.einsum("ij,ij->i", points - found.points, normal)
    return np.where(side < 0, -found.distance, found.distance)


def segment_distance(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> float:
    """The shortest distance (mm) between the segments p0-p1 and q0-q1."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e, f = d1 @ d1, d2 @ d2, d2 @ r
    c, b = d1 @ r, d1 @ d2
    denom = a * e - b * b
    s = np.clip((b * f - c * e) / denom, 0.0, 1.0) if denom > 1e-12 else 0.0
    t = (b * s + f) / e
    if t < 0.0:
        t, s = 0.0, np.clip(-c / a, 0.0, 1.0)
    elif t > 1.0:
        t, s = 1.0, np.clip((b - c) / a, 0.0, 1.0)
    return float(np.linalg.norm(p0 + s * d1 - (q0 + t * d2)))


def _screw_directions(settings: PlateSettings, normal: np.ndarray, along: np.ndarray) -> np.ndarray:
    """Unit screw directions: the inward normals (made horizontal: "transverse"), tilted by the per-hole
    angles (along the plate, across)."""
    inward = -normal
    if settings.screw_direction == "transverse":
        inward = inward * np.array([1.0, 1.0, 0.0])
        inward /= np.linalg.norm(inward, axis=1, keepdims=True)
    angles = settings.screw_angles_deg
    if not angles:
        return inward
    if len(angles) != len(normal):
        raise InputError(f"screw_angles_deg gives {len(angles)} pairs for {len(normal)} holes: one pair per hole")
    along = along - np.einsum("ij,ij->i", along, inward)[:, None] * inward
    along /= np.linalg.norm(along, axis=1, keepdims=True)
    across = np.cross(inward, along)  # towards higher angles round the bone
    tilt = np.radians(np.asarray(angles, dtype=np.float64))
    if np.any(np.abs(tilt) >= np.radians(60.0)):
        raise InputError("screw_angles_deg: a tilt of 60 degrees or more from the normal is not a plate screw")
    d = inward + np.tan(tilt[:, :1]) * along + np.tan(tilt[:, 1:]) * across
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _place_screw(hole: int, underside: np.ndarray, direction: np.ndarray, normal: np.ndarray, vertices, faces,
                 settings: PlateSettings, joints: tuple[float, float]) -> Screw:
    cos = float(-direction @ normal)
    head = underside - settings.thickness_mm / cos * direction
    hits = ray_hits(vertices, faces, head, direction)
    entering = np.flatnonzero(~hits.leaving)
    leaving = np.flatnonzero(hits.leaving)
    if len(entering) == 0 or len(leaving) == 0 or leaving[-1] < entering[0]:
        raise InputError(f"screw {hole}: its axis misses the bone (no far cortex along it)")
    first, last = entering[0], leaving[-1]
    length = float(hits.distance[last])
    if length > settings.max_screw_length_mm:
        raise InputError(f"screw {hole} cannot be placed: it needs {length:.1f} mm to the far cortex, "
                         f"{length - settings.max_screw_length_mm:.1f} mm more than max_screw_length_mm "
                         f"{settings.max_screw_length_mm:g}")
    # runs outside the bone between the first entry and the last exit: from each exit to the next entry
    between = hits.distance[first:last + 1]
    out = hits.leaving[first:last + 1]
    outside = float(sum(between[k + 1] - between[k] for k in range(len(between) - 1) if out[k] and not out[k + 1]))
    step = settings.stock_step_mm
    stock = float(np.ceil(length / step - 1e-9) * step)
    warnings = []
    if outside > _OUTSIDE_TOLERANCE_MM:
        warnings.append(f"leaves the bone for {outside:.1f} mm between the cortices")
    exit_point = hits.points[last]
    low, high = joints[0] + settings.joint_margin_mm, joints[1] - settings.joint_margin_mm
    if exit_point[2] < low:
        warnings.append(f"exits {exit_point[2] - joints[0]:.1f} mm from the distal articular end "
                        f"(margin {settings.joint_margin_mm:g} mm)")
    if exit_point[2] > high:
        warnings.append(f"exits {joints[1] - exit_point[2]:.1f} mm from the proximal articular end "
                        f"(margin {settings.joint_margin_mm:g} mm)")
    return Screw(hole, underside, head, direction, hits.points[first], exit_point, length, stock, outside,
                 float("inf"), tuple(warnings))


def _with_clearances(screws: list[Screw], settings: PlateSettings) -> tuple[Screw, ...]:
    from dataclasses import replace

    d = settings.screw_diameter_mm
    done = []
    for i, a in enumerate(screws):
        gaps = [segment_distance(a.head, a.tip, b.head, b.tip) - d for j, b in enumerate(screws) if j != i]
        clearance = min(gaps) if gaps else float("inf")
        warnings = a.warnings
        if clearance < d:
            nearest = [b.hole for j, b in enumerate(screws) if j != i][int(np.argmin(gaps))]
            warnings += (f"passes {clearance:.1f} mm from screw {nearest} (less than a screw diameter, {d:g} mm)",)
        done.append(replace(a, clearance_mm=clearance, warnings=warnings))
    return tuple(done)


def smoothed(surface: BSplineSurface, outline_uv: np.ndarray, dev: Developed, knot_mm: float) -> BSplineSurface:
    """A cubic B-spline with knots about ``knot_mm`` apart (developed mm) fitted by least squares to
    ``surface`` over the outline's parameter box (5 % wider), in the same parameters: the plate's underside
    follows the bone's shape but not the bumps of a wrinkled MRI model, whose 3.5 mm offset (the plate's
    top) left every hole drilled through JIA's tibia plate an invalid solid (the runner falls back to it)."""
    u0, u1, v0, v1 = surface.bounds
    (a0, b0), (a1, b1) = outline_uv.min(axis=0), outline_uv.max(axis=0)
    du, dv = 0.05 * (a1 - a0), 0.05 * (b1 - b0)
    a0, a1, b0, b1 = max(u0, a0 - du), min(u1, a1 + du), max(v0, b0 - dv), min(v1, b1 + dv)
    across = float(np.max(np.interp(np.array([a1]), dev.u, dev.x[_STATIONS // 2])
                          - np.interp(np.array([a0]), dev.u, dev.x[_STATIONS // 2])))
    along = float(np.interp(b1, dev.v, dev.y) - np.interp(b0, dev.v, dev.y))
    spans = [max(1, int(round(extent / knot_mm))) for extent in (across, along)]
    knots = [np.concatenate([[lo] * 4, np.linspace(lo, hi, n + 1)[1:-1], [hi] * 4])
             for (lo, hi), n in zip(((a0, a1), (b0, b1)), spans)]
    u = np.linspace(a0, a1, 6 * spans[0] + 4)
    v = np.linspace(b0, b1, 6 * spans[1] + 4)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    points = surface.evaluate(uu.ravel(), vv.ravel()).points.reshape(len(u), len(v), 3)
    bu = design_matrix(u, knots[0], 3, False, spans[0] + 3).toarray()
    bv = design_matrix(v, knots[1], 3, False, spans[1] + 3).toarray()
    rows = least_squares(bu, points.reshape(len(u), -1)).reshape(spans[0] + 3, len(v), 3)
    poles = least_squares(bv, rows.transpose(1, 0, 2).reshape(len(v), -1)).reshape(spans[1] + 3, spans[0] + 3, 3)
    return BSplineSurface(poles.transpose(1, 0, 2), knots[0], knots[1], region=surface.region,
                          bounds=np.array([a0, a1, b0, b1]))


def plate_face(region: PatchRegion, settings: PlateSettings) -> PatchRegion:
    """The bone's face a plate on ``region`` may cover: the region's heights, and ``face_angle_deg`` about the
    middle of its angles (the plate's centre line runs up that middle)."""
    middle, half = 0.5 * sum(region.angle_deg), 0.5 * settings.face_angle_deg
    return PatchRegion(region.name, region.height_mm, (middle - half, middle + half))


def plan_plate(footprint: Footprint, vertices: np.ndarray, faces: np.ndarray, joint_heights_mm: tuple[float, float],
               settings: PlateSettings, locator: TriangleLocator | None = None, *,
               smoothing_mm: float | None = None) -> PlatePlan:
    """The plate on ``footprint`` (the face of :func:`plate_face`) against the bone mesh (``vertices``,
    ``faces`` with outward normals, bone coordinates, mm), with the articular ends at ``joint_heights_mm``
    (distal, proximal; mm along the frame's z). The underside is the footprint's offset, or with
    ``smoothing_mm`` that of its :func:`smoothed` surface with knots so far apart."""
    surface = footprint.surface
    name = footprint.region.name
    outward = outward_sign(surface)
    dev = Developed(surface)
    y0, y1 = settings.end_inset_mm, dev.length_mm - settings.end_inset_mm
    if y1 - y0 < 2 * settings.end_radius_mm:
        raise InputError(f"region {name!r} is {dev.length_mm:.1f} mm long: shorter than the plate's two end radii "
                         f"({2 * settings.end_radius_mm:g} mm)")
    # the plate must fit across the face: its half width plus a margin on both sides, at every station
    ys = dev.y[(dev.y >= y0) & (dev.y <= y1)]
    below, above = dev.half_widths(ys)
    need = _half_width(settings, ys, y0, y1) + _SIDE_MARGIN_MM
    short = np.maximum(need - below, need - above)
    k = int(np.argmax(short))
    if short[k] > 0:
        height = float(np.interp(ys[k], dev.y, dev.heights))
        raise InputError(f"the plate ({2 * (need[k] - _SIDE_MARGIN_MM):.1f} mm wide) is wider than the bone's face "
                         f"in region {name!r} at {height:.1f} mm height: the face ({settings.face_angle_deg:g} deg "
                         f"round the bone) reaches {below[k]:.1f} and {above[k]:.1f} mm either side of the centre "
                         f"line, {short[k]:.1f} mm short of the half width plus {_SIDE_MARGIN_MM} mm")
    outline = dev.to_uv(outline_xy(settings, y0, y1))
    centre = dev.to_uv(np.column_stack([np.zeros(len(ys) + 2), np.concatenate([[y0], ys, [y1]])]))
    # fit samples inside the outline; the seat lifts the underside out of the mesh
    step = settings.fit_sample_mm
    hw = 0.5 * max(settings.width_mm)
    gx, gy = np.meshgrid(np.arange(-hw, hw + 1e-9, step), np.arange(y0, y1 + 1e-9, step))
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    xy = np.concatenate([xy[inside_outline(settings, xy, y0, y1)], outline_xy(settings, y0, y1)])
    uv = dev.to_uv(xy)
    underside = surface if smoothing_mm is None else smoothed(surface, outline, dev, smoothing_mm)
    points, normal, _, _ = _frames(underside, uv, outward)
    locator = locator or TriangleLocator(vertices, faces)
    gap = settings.gap_mm
    seat = max(0.0, float(gap - signed_distances(locator, points + gap * normal).min()))
    fit_points = points + (gap + seat) * normal
    fit = signed_distances(locator, fit_points)
    # holes and screws
    hole_y = hole_positions(settings, y0, y1)
    hole_xy = np.column_stack([np.zeros_like(hole_y), hole_y])
    hole_uv = dev.to_uv(hole_xy)
    h_points, h_normal, _, h_along = _frames(underside, hole_uv, outward)
    directions = _screw_directions(settings, h_normal, h_along)
    undersides = h_points + (gap + seat) * h_normal
    screws = [_place_screw(i + 1, undersides[i], directions[i], h_normal[i], vertices, faces, settings,
                           joint_heights_mm) for i in range(len(hole_y))]
    return PlatePlan(footprint, settings, underside, smoothing_mm, outline, centre, seat, outward, y1 - y0, hole_uv,
                     hole_y,
                     _with_clearances(screws, settings), fit_points, fit, joint_heights_mm)


@dataclass(frozen=True)
class Fragment:
    """A main fragment of a reduced fracture: its name and the heights it spans along the frame's axis (mm)."""

    name: str
    height_mm: tuple[float, float]


@dataclass(frozen=True)
class Fixation:
    """A plate across a fracture: the screws placed (holes within the fracture margin left empty), the empty
    holes, each fragment's screws (holes), and per fracture line its height and working length (mm along
    the plate between the nearest screws either side; None where a side has none)."""

    screws: tuple[Screw, ...]
    empty_holes: tuple[int, ...]
    fragment_screws: dict
    working_lengths_mm: tuple[tuple[float, float | None], ...]

    def summary(self) -> dict:
        return {"empty_holes": list(self.empty_holes), "fragment_screws": self.fragment_screws,
                "working_lengths_mm": [{"fracture_height_mm": round(h, 3),
                                        "working_length_mm": None if w is None else round(w, 3)}
                                       for h, w in self.working_lengths_mm]}


def fixation(plan: PlatePlan, fragments: tuple[Fragment, ...], fracture_heights_mm: tuple[float, ...],
             screws_per_fragment: int, margin_mm: float) -> Fixation:
    """The plate's screws on a reduced fracture: none whose hole lies within ``margin_mm`` (along the bone's
    axis) of a fracture height, at least ``screws_per_fragment`` in each fragment (by the hole's height);
    InputError naming the fragment that gets fewer."""
    heights = np.array([s.underside[2] for s in plan.screws])
    near = np.array([any(abs(h - f) < margin_mm for f in fracture_heights_mm) for h in heights], dtype=bool)
    kept = tuple(s for s, n in zip(plan.screws, near) if not n)
    per_fragment = {}
    for fragment in fragments:
        lo, hi = fragment.height_mm
        holes = [s.hole for s, n, h in zip(plan.screws, near, heights) if not n and lo <= h <= hi]
        if len(holes) < screws_per_fragment:
            raise InputError(f"fragment {fragment.name!r} ({lo:g} to {hi:g} mm) gets {len(holes)} screws, "
                             f"{screws_per_fragment - len(holes)} short of screws_per_fragment {screws_per_fragment} "
                             f"(no screw within fracture_margin_mm {margin_mm:g} of a fracture line): lengthen the "
                             "plate or add holes")
        per_fragment[fragment.name] = holes
    working = []
    for fracture in fracture_heights_mm:
        below = [plan.hole_y[s.hole - 1] for s, h in zip(kept, (s.underside[2] for s in kept)) if h < fracture]
        above = [plan.hole_y[s.hole - 1] for s, h in zip(kept, (s.underside[2] for s in kept)) if h > fracture]
        span = float(min(above) - max(below)) if below and above else None
        working.append((float(fracture), span))
    return Fixation(kept, tuple(s.hole for s, n in zip(plan.screws, near) if n), per_fragment, tuple(working))
