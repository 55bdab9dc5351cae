"""Contour curves of the three regions (DESIGN.md step 3), as cubic B-splines in bone coordinates.

- distal: half-planes through the mechanical axis at the configured angles,
  each curve from the apex hole (radius ``apex_hole_radius_mm`` about the
  axis) to the distal region boundary;
- proximal: half-planes through the local proximal axis, from the apex hole
  down to the proximal region boundary;
- shaft: closed sections perpendicular to the mechanical axis, each starting
  at angle 0 (lateral) and running lateral -> anterior -> medial, the number of
  sections chosen so a cubic loft through them describes the shaft within
  the shaft tolerance.

Angles run from lateral (0) towards anterior (90) in bone coordinates, where
every tibia looks like a right one (see ``anatomy.frame``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.interpolate import CubicSpline

from bonecad.anatomy.frame import AnatomicalFrame
from bonecad.errors import FitError
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.settings import CurvesSettings
from bonecad.mesh.sections import LevelSections, section_mesh
from bonecad.splines.curve import BSplineCurve, CurveFit, fit_curve

REGIONS = ("distal", "shaft", "proximal")
EndRegion = Literal["distal", "proximal"]


@dataclass(frozen=True)
class ContourCurve:
    """One rebuilt contour curve (bone coordinates, mm) and how well it fits its raw section."""

    region: str
    index: int
    curve: BSplineCurve
    raw_points: np.ndarray  # (m, 3) the section polyline it was fitted to
    tolerance_mm: float
    max_deviation_mm: float
    rms_deviation_mm: float
    angle_deg: float | None = None  # half-plane angle (distal, proximal)
    level_mm: float | None = None  # height above the plafond centre (shaft)
    repairs: tuple[str, ...] = ()

    @property
    def name(self) -> str:
        if self.angle_deg is not None:
            return f"{self.region}_{self.index:02d}_{self.angle_deg:g}deg"
        return f"{self.region}_{self.index:02d}_z{self.level_mm:.0f}mm"  # STEP names take no dots

    @property
    def angle(self) -> float:
        """``angle_deg`` of a half-plane curve (distal, proximal); ValueError for a shaft curve."""
        if self.angle_deg is None:
            raise ValueError(f"{self.name}: not a half-plane curve (no angle)")
        return self.angle_deg

    @property
    def level(self) -> float:
        """``level_mm`` of a shaft curve; ValueError for a half-plane curve."""
        if self.level_mm is None:
            raise ValueError(f"{self.name}: not a shaft curve (no level)")
        return self.level_mm

    @property
    def within_tolerance(self) -> bool:
        return self.max_deviation_mm <= self.tolerance_mm


@dataclass(frozen=True)
class ContourSet:
    """The three regions' contour curves in bone coordinates, with the frame that maps them back."""

    frame: AnatomicalFrame
    distal: tuple[ContourCurve, ...]
    shaft: tuple[ContourCurve, ...]
    proximal: tuple[ContourCurve, ...]
    local_axis_bone: np.ndarray  # (2, 3) plateau centre and lowest proximal centroid, bone coordinates
    shaft_fit_error_mm: float  # predicted loft error between shaft sections (99th percentile)
    notes: tuple[str, ...] = field(default=())

    def region(self, name: str) -> tuple[ContourCurve, ...]:
        return getattr(self, name)

    def all_curves(self) -> list[ContourCurve]:
        return [*self.distal, *self.shaft, *self.proximal]

    def summary(self) -> dict:
        """Per-region worst deviation and tolerance, and whether every curve met it."""
        out = {}
        for name in REGIONS:
            curves = self.region(name)
            out[name] = {
                "curves": len(curves),
                "control_points_per_curve": curves[0].curve.count if curves else 0,
                "tolerance_mm": curves[0].tolerance_mm if curves else None,
                "worst_max_deviation_mm": round(max(c.max_deviation_mm for c in curves), 4) if curves else None,
                "mean_rms_deviation_mm": (round(float(np.mean([c.rms_deviation_mm for c in curves])), 4)
                                          if curves else None),
                "within_tolerance": sum(c.within_tolerance for c in curves),
            }
        return out


def bone_coordinates(bone: BoneMesh, frame: AnatomicalFrame) -> tuple[np.ndarray, np.ndarray]:
    """The mesh's working copy (``BoneMesh.work``: the shape, in as many triangles as the tolerance needs) in
    bone coordinates; faces flipped for a left tibia so normals still point out."""
    vertices = frame.to_bone(bone.work.vertices)
    faces = bone.work.faces[:, ::-1] if frame.mirrored else bone.work.faces
    return vertices, faces


def _runs(mask: np.ndarray) -> list[np.ndarray]:
    """Index runs where ``mask`` is true, treating the array as cyclic."""
    n = len(mask)
    if mask.all():
        return [np.arange(n)]
    start = int(np.argmin(mask))  # a False entry: runs never wrap past it
    rolled = np.roll(mask, -start)
    edges = np.diff(np.concatenate([[0], rolled.astype(int), [0]]))
    begins, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [(np.arange(b, e) + start) % n for b, e in zip(begins, ends)]


def _crossing(p: np.ndarray, q: np.ndarray, fp: float, fq: float) -> np.ndarray:
    """The point between p and q where a linear function with values fp, fq vanishes."""
    return p + (fp / (fp - fq)) * (q - p)


def half_plane_polyline(
    vertices: np.ndarray,
    faces: np.ndarray,
    axis_point: np.ndarray,
    axis_dir: np.ndarray,
    reference_dir: np.ndarray,
    angle_deg: float,
    boundary_z: float,
    towards: int,
    apex_radius: float,
) -> tuple[np.ndarray, list[str]]:
    """Section polyline in one half-plane about an axis, from the apex hole to the boundary plane.

    ``towards`` is -1 for a distal curve (region below ``boundary_z``) and +1
    for a proximal one. Returns (m, 3) points and notes on what was dropped.
    """
    e1 = reference_dir - (reference_dir @ axis_dir) * axis_dir
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis_dir, e1)
    theta = np.radians(angle_deg)
    d = np.cos(theta) * e1 + np.sin(theta) * e2
    normal = np.cross(axis_dir, d)
    loops = section_mesh(vertices, faces, axis_point, normal).loops()
    notes = []
    if not loops:
        raise FitError(f"the {angle_deg:g} degree half-plane misses the bone")
    pieces, candidates = 0, []
    for loop in loops:
        r = (loop - axis_point) @ d
        z = loop[:, 2]
        n = len(loop)
        inside = (r > apex_radius) & ((z - boundary_z) * towards > 0)
        for run in _runs(inside):
            pieces += 1
            # Ends: exact crossings of the apex circle (r = apex_radius) and the boundary plane.
            before, after = (run[0] - 1) % n, (run[-1] + 1) % n
            end_a = _end_point(loop, r, z, before, run[0], apex_radius, boundary_z, towards)
            end_b = _end_point(loop, r, z, run[-1], after, apex_radius, boundary_z, towards)
            candidates.append((run, loop, end_a, end_b))
    if not candidates:
        raise FitError(f"the {angle_deg:g} degree half-plane holds no bone beyond the apex hole")
    # the curve runs from the apex hole to the boundary plane: the longest piece that does (a piece that
    # leaves the apex hole and comes back to it, where the bone bulges round the axis, is not the curve)
    spanning = [c for c in candidates if {c[2][1], c[3][1]} == {"apex", "boundary"}]
    if not spanning:
        kinds = max(candidates, key=lambda c: len(c[0]))
        raise FitError(
            f"the {angle_deg:g} degree half-plane section does not run from the apex to the region boundary "
            f"(its ends meet the {kinds[2][1]} and the {kinds[3][1]})"
        )
    run, loop, end_a, end_b = max(spanning, key=lambda c: len(c[0]))
    if pieces > 1:
        notes.append(f"dropped {pieces - 1} spurious piece(s) of section in the half-plane")
    points = np.vstack([end_a[0], loop[run], end_b[0]])
    if (end_a[1], end_b[1]) == ("boundary", "apex"):
        points = points[::-1]
    return points, notes


def _end_point(loop, r, z, i, j, apex_radius, boundary_z, towards):
    """Where the loop leaves the region between points i and j, and through which limit."""
    fr_i, fr_j = r[i] - apex_radius, r[j] - apex_radius
    fz_i, fz_j = (z[i] - boundary_z) * towards, (z[j] - boundary_z) * towards
    if fz_j <= 0 < fz_i or fz_i <= 0 < fz_j:
        return _crossing(loop[i], loop[j], fz_i, fz_j), "boundary"
    return _crossing(loop[i], loop[j], fr_i, fr_j), "apex"


def _closed_section(levels: LevelSections, level: float, centre_xy: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Outer loop at height ``level``, starting on the ray from ``centre_xy`` towards +x (lateral)."""
    loops = levels.at(level).loops()
    if not loops:
        raise FitError(f"no shaft section at {level:.1f} mm")
    notes = [f"dropped {len(loops) - 1} extra section loop(s)"] if len(loops) > 1 else []
    loop = max(loops, key=lambda lp: abs(_polygon_area(lp)))
    rel = loop[:, :2] - centre_xy
    nxt = np.roll(rel, -1, axis=0)
    # Edges crossing the +x ray from the centre (y changes sign, crossing x > 0).
    crosses = (rel[:, 1] <= 0) & (nxt[:, 1] > 0)
    t = np.where(crosses, -rel[:, 1] / np.where(crosses, nxt[:, 1] - rel[:, 1], 1.0), 0.0)
    x_at = rel[:, 0] + t * (nxt[:, 0] - rel[:, 0])
    candidates = np.flatnonzero(crosses & (x_at > 0))
    if len(candidates) == 0:
        raise FitError(f"the shaft section at {level:.1f} mm does not surround the axis")
    i = candidates[np.argmax(x_at[candidates])]
    start = loop[i] + t[i] * (loop[(i + 1) % len(loop)] - loop[i])
    ordered = np.vstack([start, np.roll(loop, -(i + 1), axis=0)])
    return ordered, notes


def _polygon_area(loop: np.ndarray) -> float:
    x, y = loop[:, 0], loop[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _radial_profile(loop: np.ndarray, centre_xy: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Distance from ``centre_xy`` to the loop at each angle (radians), by periodic polar interpolation."""
    rel = loop[:, :2] - centre_xy
    phi = np.arctan2(rel[:, 1], rel[:, 0])
    order = np.argsort(phi)
    return np.interp(angles, phi[order], np.linalg.norm(rel, axis=1)[order], period=2 * np.pi)


def choose_shaft_levels(
    levels: LevelSections,
    low: float,
    high: float,
    centre_at,
    tolerance_mm: float,
    harmonics: int,
    min_spacing_mm: float,
    fixed_count: int = 0,
) -> tuple[np.ndarray, float, float]:
    """Heights of the shaft sections, and the predicted loft error (99th percentile, max; mm) between them.

    The shaft is sampled every 2 mm as radial profiles, smoothed to the
    ``harmonics`` a closed curve of the shaft's control-point count can
    follow; the fewest equally spaced sections whose cubic interpolation
    along the axis reproduces 99 % of the samples within ``tolerance_mm``
    are chosen (or ``fixed_count`` of them), never closer than
    ``min_spacing_mm`` (a rough mesh, e.g. a voxel staircase, cannot be
    followed by sections: the caller reports the error reached).
    """
    fine = np.linspace(low, high, max(8, int(np.ceil((high - low) / 2.0)) + 1))
    angles = np.linspace(0.0, 2 * np.pi, 90, endpoint=False)
    profiles = np.empty((len(fine), len(angles)))
    for k, level in enumerate(fine):
        centre = centre_at(level)
        loop, _ = _closed_section(levels, level, centre)
        profiles[k] = _radial_profile(loop, centre, angles)
    spectrum = np.fft.rfft(profiles, axis=1)
    spectrum[:, harmonics + 1 :] = 0.0
    profiles = np.fft.irfft(spectrum, n=len(angles), axis=1)
    most = max(4, int((high - low) / min_spacing_mm) + 1)
    candidates = [fixed_count] if fixed_count else range(4, most + 1)
    for count in candidates:
        idx = np.round(np.linspace(0, len(fine) - 1, count)).astype(int)
        error = np.abs(CubicSpline(fine[idx], profiles[idx], axis=0)(fine) - profiles)
        p99, worst = float(np.percentile(error, 99)), float(error.max())
        if p99 <= tolerance_mm or fixed_count:
            break
    return fine[idx], p99, worst


@dataclass(frozen=True)
class ShaftCurves:
    """The shaft's closed sections, and the predicted error of a cubic loft through them (mm)."""

    curves: tuple[ContourCurve, ...]
    loft_error_p99_mm: float
    loft_error_max_mm: float


def _proximal_axis(frame: AnatomicalFrame) -> tuple[np.ndarray, np.ndarray]:
    """The local proximal axis in bone coordinates (plateau centre, lowest proximal centroid) and its
    unit direction towards the plateau."""
    local_bone = frame.to_bone(frame.local_proximal_axis)
    local_dir = local_bone[0] - local_bone[1]
    return local_bone, local_dir / np.linalg.norm(local_dir)


def fit_section(raw: np.ndarray, count: int, *, periodic: bool, settings: CurvesSettings, notes: list[str]
                ) -> CurveFit:
    """The contour curve of one section polyline (mm), its repairs appended to ``notes``.

    A curve that misses its section by more than ``settings.stiff_refit_above_mm``
    has overshot where the section's points are sparse (a coarse or rough mesh:
    a control point with no data near it swings out, and the outlier test then
    drops real points); it is fitted again with the stiffer
    ``settings.stiff_refit_fairness``, which bridges such spans, and the closer
    of the two is kept.
    """
    fit = fit_curve(raw, count, periodic=periodic, degree=settings.degree)
    if fit.max_deviation_mm > settings.stiff_refit_above_mm:
        stiff = fit_curve(raw, count, periodic=periodic, degree=settings.degree, fairness=settings.stiff_refit_fairness)
        if stiff.max_deviation_mm < fit.max_deviation_mm:
            notes.append(f"refitted stiffer: the first fit overshot by {fit.max_deviation_mm:.1f} mm where the "
                         f"section's points are sparse")
            fit = stiff
    if fit.outliers:
        notes.append(f"bridged {fit.outliers} outlying section point(s) (peaks from holes or artefacts)")
    return fit


def end_curves(bone: BoneMesh, frame: AnatomicalFrame, region: EndRegion, *,
               settings: CurvesSettings) -> tuple[ContourCurve, ...]:
    """The half-plane curves of one end region (bone coordinates): distal ones about the mechanical
    axis, proximal ones about the local proximal axis, each from the apex hole to the region boundary."""
    vertices, faces = bone_coordinates(bone, frame)
    x_axis = np.array([1.0, 0.0, 0.0])
    if region == "distal":
        axis_point, axis_dir, boundary, towards = np.zeros(3), np.array([0.0, 0.0, 1.0]), frame.distal_boundary_mm, -1
        angles, count, tol = settings.distal_angles_deg, settings.distal_control_points, settings.distal_tolerance_mm
    else:
        local_bone, axis_dir = _proximal_axis(frame)
        axis_point, boundary, towards = local_bone[0], frame.proximal_boundary_mm, +1
        angles, count = settings.proximal_angles_deg, settings.proximal_control_points
        tol = settings.proximal_tolerance_mm
    curves = []
    for i, angle in enumerate(angles):
        raw, notes = half_plane_polyline(vertices, faces, axis_point, axis_dir, x_axis, float(angle),
                                         boundary, towards, settings.apex_hole_radius_mm)
        fit = fit_section(raw, count, periodic=False, settings=settings, notes=notes)
        curves.append(ContourCurve(region, i, fit.curve, raw, tol, fit.max_deviation_mm,
                                   fit.rms_deviation_mm, angle_deg=float(angle), repairs=tuple(notes)))
    return tuple(curves)


def shaft_curves(bone: BoneMesh, frame: AnatomicalFrame, *, settings: CurvesSettings) -> ShaftCurves:
    """The shaft's closed sections perpendicular to the mechanical axis (bone coordinates).

    They start on the ray at angle 0 from a centre line that runs from the
    mechanical axis (distal boundary) to the local axis (proximal boundary), so
    they start where curve 0 of each end region ends.
    """
    vertices, faces = bone_coordinates(bone, frame)
    z_d, z_p = frame.distal_boundary_mm, frame.proximal_boundary_mm
    local_bone, _ = _proximal_axis(frame)

    def centre_at(level: float) -> np.ndarray:
        share = np.clip((level - z_d) / (z_p - z_d), 0.0, 1.0)
        return share * local_bone[1, :2]

    tol, count = settings.shaft_tolerance_mm, settings.shaft_control_points
    stack = LevelSections(vertices, faces, np.zeros(3), np.array([0.0, 0.0, 1.0]))
    levels, predicted, worst = choose_shaft_levels(
        stack, z_d, z_p, centre_at, tol, count // 2, settings.shaft_min_spacing_mm, settings.shaft_sections)
    shaft = []
    for i, level in enumerate(levels):
        raw, notes = _closed_section(stack, float(level), centre_at(level))
        fit = fit_section(raw, count, periodic=True, settings=settings, notes=notes)
        shaft.append(ContourCurve("shaft", i, fit.curve, raw, tol, fit.max_deviation_mm,
                                  fit.rms_deviation_mm, level_mm=float(level), repairs=tuple(notes)))
    return ShaftCurves(tuple(shaft), float(predicted), float(worst))


def assemble_contours(frame: AnatomicalFrame, distal: tuple[ContourCurve, ...], shaft: ShaftCurves,
                      proximal: tuple[ContourCurve, ...]) -> ContourSet:
    """The three regions' curves as one set, with notes on the shaft loft."""
    tol = shaft.curves[0].tolerance_mm if shaft.curves else 0.0
    notes = [
        f"{len(shaft.curves)} shaft sections: a cubic loft through them follows 99 % of the shaft within "
        f"{shaft.loft_error_p99_mm:.3f} mm (worst {shaft.loft_error_max_mm:.3f} mm) of its sections sampled every 2 mm"
    ]
    if shaft.loft_error_p99_mm > tol:
        notes.append(f"shaft loft error {shaft.loft_error_p99_mm:.3f} mm is above the {tol} mm tolerance")
    return ContourSet(frame, distal, shaft.curves, proximal, _proximal_axis(frame)[0], shaft.loft_error_p99_mm,
                      tuple(notes))


def contour_curves(bone: BoneMesh, frame: AnatomicalFrame, *, settings: CurvesSettings) -> ContourSet:
    """Section the bone and rebuild every contour curve as a cubic B-spline (bone coordinates), one
    region after another (the runner fits the proximal region on the second core instead)."""
    return assemble_contours(frame, end_curves(bone, frame, "distal", settings=settings),
                             shaft_curves(bone, frame, settings=settings),
                             end_curves(bone, frame, "proximal", settings=settings))
