"""The template T-mesh: one T-spline topology fitted to every tibia (issue 21).

Every tibia gets the same T-mesh: the same knot lines, T-junctions and
control-point order, in one fixed parameter domain (``[template]`` settings,
template mm). A bone's own parameterisation (:mod:`.skinning`: s the angle
about the mechanical axis, distally, or the local proximal axis, proximally,
from lateral towards anterior; t the meridian arc from the distal apex ring,
the height along the shaft, the meridian arc to the proximal apex ring) is
mapped onto the template's following the anatomy (``to_template``): s by
its period, turned on the distal end to the ankle's own lateral (torsion);
t by each region's share (distal, shaft, proximal, their boundaries from the
frame), the proximal meridians bent so that the tibial tuberosity's height
lands at one template t. So control point i sits on the same anatomical
place on every bone.

The fit is the model's (:mod:`.model`) without refinement: skin the contour
curves on the template mesh, project the mesh points, then parameter
corrections (projection + re-solve, ``fit_adaptive`` with no refinement
round), with the apex rings held at their parameters.

The T-mesh (the designed layout, ``template_mesh``): ``s_intervals`` s-lines
round the ends, where the plateau rim, the malleolus and the tuberosity bend
sharply; on the shaft only ``shaft_s_intervals`` of them continue (the
others end in T-junctions a few rows into the shaft); t-lines uniform per
region; next to each apex ring only every other s-line reaches the ring.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np

from bonecad.anatomy.frame import AnatomicalFrame
from bonecad.contours.curves import ContourSet, bone_coordinates
from bonecad.errors import FitError
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.mesh.sampling import fit_samples
from bonecad.occ.pickling import ShapePickling
from bonecad.settings import TemplateSettings, TSplineSettings
from bonecad.splines.tspline import TMesh, TSpline
from bonecad.splines.tspline.fit import FitTolerances, fit_adaptive, initial_parameters, solve_control_points
from bonecad.tspline_model.caps import ApexCap
from bonecad.tspline_model.model import apex_caps, hole_masks, occ_shape, ring_constraints
from bonecad.tspline_model.skinning import Parameterisation, arc_samples, curve_data, parameterisation


@dataclass(frozen=True)
class TemplateFit:
    """The template fitted to one tibia (bone coordinates, mm).

    mesh : the template T-mesh; control_points : (n, 3), in the template's fixed order; share_within :
    weighted share of the surface within ``within_mm``; max_mm, rms_mm : distances of the fit points;
    cpu_s : CPU seconds. Pickles small (~0.4 MB: the T-spline's Bezier extraction, ~10 MB, is rebuilt on use).
    """

    mesh: TMesh
    control_points: np.ndarray
    within_mm: float
    share_within: float
    max_mm: float
    rms_mm: float
    cpu_s: float

    @cached_property
    def tspline(self) -> TSpline:
        return TSpline(self.mesh, self.control_points, np.ones(len(self.control_points)))

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "tspline"}

    def summary(self) -> dict:
        return {"control_points": len(self.control_points), f"share_within_{self.within_mm:g}_mm":
                round(self.share_within, 5), "max_mm": round(self.max_mm, 4), "rms_mm": round(self.rms_mm, 4),
                "cpu_s": round(self.cpu_s, 3)}


def region_bounds(settings: TemplateSettings) -> np.ndarray:
    """(4,) template t of the distal apex ring, the two region boundaries and the proximal apex ring."""
    st = settings
    return np.cumsum([0.0, st.distal_length_mm, st.shaft_length_mm, st.proximal_length_mm])


@lru_cache(maxsize=4)
def template_mesh(settings: TemplateSettings) -> TMesh:
    """The template T-mesh (see the module docstring); the same for every bone."""
    st = settings
    if st.s_intervals != 2 * st.shaft_s_intervals:
        raise FitError(f"template s_intervals ({st.s_intervals}) must be twice shaft_s_intervals "
                       f"({st.shaft_s_intervals})")
    bounds = region_bounds(st)
    counts = (st.distal_t_intervals, st.shaft_t_intervals, st.proximal_t_intervals)
    t_knots = np.concatenate([[0.0]] + [np.linspace(a, b, n + 1)[1:] for a, b, n in zip(bounds, bounds[1:], counts)])
    mesh = TMesh.grid(np.arange(st.s_intervals) * (st.s_period_mm / st.s_intervals), t_knots,
                      s_period=st.s_period_mm)
    t_edges = mesh.t_edges.copy()
    t_n = mesh.shape[1]
    ring_rows = 3 + st.apex_rows  # t-line index where the odd s-lines end next to the rings
    # t-line indices of the region boundaries: knots 0.. are lines 2..; boundary k is knot sum(counts[:k])
    lo = 2 + st.distal_t_intervals + st.shaft_transition_rows
    hi = 2 + st.distal_t_intervals + st.shaft_t_intervals - st.shaft_transition_rows
    for i in range(1, st.s_intervals, 2):
        t_edges[i, :ring_rows] = False
        t_edges[i, t_n - 1 - ring_rows:] = False
        t_edges[i, lo:hi] = False
    out = mesh.with_edges(mesh.s_edges, t_edges)
    out.validate()
    return out


@lru_cache(maxsize=2)
def _template_blank(settings: TemplateSettings) -> TSpline:
    """The template T-spline with zero control points and its Bezier extraction built (0.25 s CPU, ~10 MB),
    which every shape on the template shares (a shape model projects onto tens of them)."""
    mesh = template_mesh(settings)
    blank = TSpline(mesh, np.zeros((len(mesh.anchors), 3)), np.ones(len(mesh.anchors)))
    blank.extraction  # noqa: B018  (built once here, handed on by with_control_points)
    return blank


def template_tspline(control_points: np.ndarray, settings: TemplateSettings) -> TSpline:
    """The template T-spline with the given control points ((n, 3) mm, template order): a mean shape, a morph."""
    blank = _template_blank(settings)
    cp = np.asarray(control_points, dtype=np.float64)
    if cp.shape != blank.control_points.shape:
        raise FitError(f"the template has {len(blank.control_points)} control points, got an array of shape "
                       f"{cp.shape}")
    return blank.with_control_points(cp)


@dataclass(frozen=True)
class AnatomicalWarp:
    """How a bone's own (s, t) bend to follow its anatomy on the template (see ``to_template``).

    ankle_turn_deg : direction of the ankle's lateral axis (degrees from the frame's lateral towards anterior);
    meridian_angle_deg, tuberosity_share : (m,) the proximal meridians' angles (degrees) and the share of each
    one's arc from the apex ring (0) to the shaft boundary (1) at which it comes down to the tuberosity's height.
    """

    ankle_turn_deg: float
    meridian_angle_deg: np.ndarray
    tuberosity_share: np.ndarray


def anatomical_warp(contours: ContourSet, *, ankle_turn_deg: float, tuberosity_height_mm: float) -> AnatomicalWarp:
    """The warp of a bone with these contour curves, ankle direction (``anatomy.morphometry.ankle_turn_deg``)
    and tuberosity height (bone z, mm; ``anatomy.morphometry.tibial_tuberosity``). Raises FitError when a
    proximal meridian does not come down to the tuberosity's height (a tuberosity below the proximal region)."""
    angles, shares = [], []
    for c in contours.proximal:
        points, share, _ = arc_samples(c.curve, 801)
        above = np.nonzero(points[::-1, 2] >= tuberosity_height_mm)[0]  # walking up from the shaft boundary
        if not len(above) or above[0] == 0:
            raise FitError(f"the tibial tuberosity ({tuberosity_height_mm:.1f} mm above the plafond centre) lies "
                           f"outside the proximal meridian at {c.angle % 360.0:.0f} degrees")
        angles.append(c.angle % 360.0)
        shares.append(share[len(share) - 1 - above[0]])
    order = np.argsort(angles)
    return AnatomicalWarp(float(ankle_turn_deg), np.asarray(angles)[order], np.asarray(shares)[order])


def to_template(par: Parameterisation, s: np.ndarray, t: np.ndarray, settings: TemplateSettings,
                warp: AnatomicalWarp) -> tuple[np.ndarray, np.ndarray]:
    """A bone's (s, t) (its :class:`Parameterisation`) -> the template's, following the anatomy.

    t linearly per region, except on the proximal meridians, bent piecewise linearly so that the
    tuberosity's height lands at ``[template] tuberosity_share`` of them: the tuberosity sits at one template t
    whatever the plateau's depth. s by the period, its angle counted from the ankle's own lateral on the
    distal end and from the frame's lateral on the proximal end, the turn fading linearly along the shaft: the
    tibia's torsion turns its distal end against its plateau, and the malleolus lies at one template angle."""
    bounds = region_bounds(settings)
    t_template = np.interp(t, [0.0, par.t_distal, par.t_proximal, par.t_end], bounds)
    proximal = t > par.t_proximal
    share = (par.t_end - t[proximal]) / (par.t_end - par.t_proximal)  # 0 at the apex ring
    q = np.interp(np.mod(s[proximal], par.s_period) * (360.0 / par.s_period), warp.meridian_angle_deg,
                  warp.tuberosity_share, period=360.0)
    target = settings.tuberosity_share
    bent = np.where(share < q, share * (target / q), target + (share - q) * ((1.0 - target) / (1.0 - q)))
    t_template[proximal] = bounds[3] - bent * (bounds[3] - bounds[2])
    turn = warp.ankle_turn_deg / 360.0 * par.s_period * np.interp(t_template, bounds[1:3], [1.0, 0.0])
    return np.mod(s - turn, par.s_period) * (settings.s_period_mm / par.s_period), t_template


def surface_targets(bone: BoneMesh, frame: AnatomicalFrame, settings: TemplateSettings, *,
                    apex_hole_radius_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The surface the template covers, as the fit's points (bone coordinates, mm) and their area weights
    (mm^2): the mesh's fit samples outside the two apex holes (the caps close those)."""
    vertices, weights = fit_samples(*bone_coordinates(bone, frame), settings.fit_point_spacing_mm)
    hole_d, hole_p = hole_masks(vertices, frame, apex_hole_radius_mm)
    keep = ~(hole_d | hole_p) & (weights > 0)
    return vertices[keep], weights[keep]


def fit_template(bone: BoneMesh, frame: AnatomicalFrame, contours: ContourSet, settings: TemplateSettings, *,
                 apex_hole_radius_mm: float, ankle_turn_deg: float, tuberosity_height_mm: float) -> TemplateFit:
    """Fit the template T-mesh to a tibia: skin its contour curves, then fit its surface with parameter
    correction and no refinement (see the module docstring).

    contours : the bone's contour curves (``contour_curves`` with the same frame); apex_hole_radius_mm :
    their apex hole radius; ankle_turn_deg, tuberosity_height_mm : its ankle's lateral axis and tibial
    tuberosity (``anatomical_warp``). Raises FitError when the curves cannot be parameterised.
    """
    st = settings
    clock = time.process_time()
    par = parameterisation(contours)
    pts, w = surface_targets(bone, frame, st, apex_hole_radius_mm=apex_hole_radius_mm)

    warp = anatomical_warp(contours, ankle_turn_deg=ankle_turn_deg, tuberosity_height_mm=tuberosity_height_mm)
    data = curve_data(contours, par)
    s_c, t_c = to_template(par, data.s, data.t, st, warp)
    mesh = template_mesh(st)
    ts0 = solve_control_points(_template_blank(st), s_c, t_c, data.points, fairness=st.fairness_weight)
    ring_p, ring_s, ring_t, ring_w = ring_constraints(contours, par, apex_hole_radius_mm)
    ring_s, ring_t = to_template(par, ring_s, ring_t, st, warp)

    s0, t0, _ = initial_parameters(ts0, pts)
    share, within = st.target_share_within_mm
    # no refinement round (max_rounds 0): the refinement controls are never read
    tol = FitTolerances(share_within=(share, within), max_deviation_mm=st.max_deviation_mm, rms_mm=st.rms_mm,
                        max_control_points=ts0.n_control, max_rounds=0, min_element_mm=np.inf, mark_fraction=0.0,
                        noise_factor=0.0, split_anisotropy=np.inf, mark_deficit_factor=0.0)
    fit = fit_adaptive(ts0, pts, w, s=s0, t=t0, tolerances=tol, fairness=st.fit_fairness_weight,
                       corrections=st.corrections, constraints=(ring_p, ring_s, ring_t, ring_w))
    return TemplateFit(mesh, fit.tspline.control_points, within, fit.stats.share_within, fit.stats.max_mm,
                       fit.stats.rms_mm, time.process_time() - clock)


@dataclass(frozen=True)
class BoneCoordinates:
    """The identity map of a shape built in bone coordinates (a mean shape, a morph): no scanner frame."""

    def to_scanner(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(points, dtype=np.float64)


@dataclass(frozen=True)
class TemplateShape(ShapePickling):
    """A template T-spline as a closed solid (bone coordinates, mm): the tube, its two flat apex caps,
    the sewn OpenCascade solid and its named faces (the T-spline model's exporters write it)."""

    tspline: TSpline
    caps: tuple[ApexCap, ApexCap]
    shape: object
    face_names: tuple[tuple[str, object], ...]
    frame: BoneCoordinates


def template_shape(ts: TSpline, settings: TemplateSettings, *, faces: TSplineSettings) -> TemplateShape:
    """The closed solid of a template T-spline (a mean shape or a morph, no mesh behind it): each apex
    hole closed by a cap whose pole lies in the plane of its ring (the holes are a few mm wide)."""
    bounds = region_bounds(settings)
    ring = ts.evaluate(np.linspace(0.0, settings.s_period_mm, 64, endpoint=False), np.full(64, bounds[3])).points
    below = ts.evaluate(np.linspace(0.0, settings.s_period_mm, 64, endpoint=False),
                        np.full(64, bounds[3] - settings.proximal_length_mm / settings.proximal_t_intervals)).points
    top, under = ring.mean(axis=0), below.mean(axis=0)
    par = Parameterisation(settings.s_period_mm, bounds[1], bounds[2], bounds[3], 0.0, 0.0, np.stack([top, under]))
    none = np.zeros((0, 3))
    caps = apex_caps(ts, par, none, none)
    frame = BoneCoordinates()
    shape, names = occ_shape(ts, caps, par, frame, settings=faces)  # faces: the face layout of the model's solid
    return TemplateShape(ts, caps, shape, tuple(names), frame)
