"""The T-spline tibia model (DESIGN.md step 5): one C2 T-spline tube from the
distal to the proximal apex ring, fitted to the whole polygonal model, with
two quad-topology apex caps; converted to OpenCascade by Bezier extraction.

Stages (each a function of numpy data; OpenCascade only in ``occ_shape``):

1. parameterise and skin the three contour-curve sets on one T-mesh
   (:mod:`.skinning`);
2. fit the T-spline to every mesh vertex outside the apex holes (area
   weights; on a coarse mesh its edge midpoints instead), with parameter
   correction and error-driven local refinement (:mod:`.fit`), until the
   tolerances hold or the control-point budget is hit;
3. fit a tensor-product B-spline to the same points and tolerances by
   refining whole knot lines, for the control-point comparison;
4. cap the apex holes (:mod:`.caps`), extract Bezier patches, merge each
   tensor-product block of them into one B-spline face, sew the faces into a
   closed solid in scanner coordinates (outward faces, positive volume).
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order
from scipy.sparse.linalg import spsolve

from bonecad.anatomy.frame import AnatomicalFrame
from bonecad.contours.curves import ContourSet, bone_coordinates
from bonecad.errors import KernelError
from bonecad.occ.pickling import ShapePickling
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.mesh.sampling import fit_sample_mesh
from bonecad.mesh.working import coarser_copy
from bonecad.settings import TSplineSettings
from bonecad.splines.tspline import TSpline

from bonecad.tspline_model.caps import ApexCap, build_cap
from bonecad.splines.folds import FOLD_TURN_DEG
from bonecad.splines.tspline.fit import (FitResult, FitStats, FitTolerances, element_turns_deg, fit_adaptive,
                                         initial_parameters, local_noise_mm, noise_level_mm)
from bonecad.tspline_model.skinning import Parameterisation, initial_mesh, parameterisation, skin

log = logging.getLogger(__name__)

#: Sewing tolerances tried in turn (mm).
_SEWING_TOLERANCES_MM = (1e-4, 1e-3, 1e-2)


@dataclass(frozen=True)
class TSplineModel(ShapePickling):
    """The fitted T-spline model of one tibia.

    tspline : the tube (bone coordinates, mm); caps : the two apex caps.
    control_points : the tube's control points (caps: ``cap_control_points``).
    tensor_product_control_points : control points of the tensor-product
        B-spline fitted to the same tolerance (None when not computed);
        tensor_product_converged : whether that fit met the tolerances.
    fit : the adaptive fit (final stats, history, why it stopped).
    staircase_voxel_mm : the voxel size when the mesh is a voxel staircase
        (vertices on a lattice: its steps then count as the data's noise), else 0.
    noise_level_mm : the mesh's noise level (``noise_level_mm`` at the settings'
        ``noise_level_radius_mm`` and ``noise_level_quantile``); at or above ``rough_noise_level_mm`` the mesh
        counts as rough and the fit stops at it (``fit_adaptive(noise_level=...)``).
    shape : OCP TopoDS_Shape (closed solid), scanner coordinates; face_names :
        (name, TopoDS_Face) of every face of it ("distal", "shaft", "proximal",
        "distal_apex_cap", "proximal_apex_cap").
    """

    tspline: TSpline
    caps: tuple[ApexCap, ApexCap]
    parameterisation: Parameterisation
    fit: FitResult
    skin_residual_mm: tuple[float, float]
    tensor_product_control_points: int | None
    tensor_product_converged: bool | None
    tensor_product_fit: FitResult | None
    shape: object
    face_names: tuple[tuple[str, object], ...]
    frame: AnatomicalFrame
    staircase_voxel_mm: float = 0.0
    noise_level_mm: float = 0.0
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def control_points(self) -> int:
        return self.tspline.n_control

    @property
    def cap_control_points(self) -> int:
        return sum(c.tspline.n_control for c in self.caps)

    @property
    def control_point_ratio(self) -> float | None:
        if not self.tensor_product_control_points:
            return None
        return self.control_points / self.tensor_product_control_points

    def summary(self) -> dict:
        """JSON-ready figures: counts, fit statistics, continuity of the caps, timings."""
        return {
            "control_points": self.control_points,
            "cap_control_points": self.cap_control_points,
            "bezier_elements": self.tspline.extraction.n_elements,
            "tensor_product_control_points": self.tensor_product_control_points,
            "tensor_product_converged": self.tensor_product_converged,
            "control_point_ratio": None if self.control_point_ratio is None else round(self.control_point_ratio, 4),
            "fit": self.fit.stats.to_dict(),
            "fit_converged": self.fit.converged,
            "fit_stopped": self.fit.stopped,
            "fit_folded_elements": self.fit.folded_elements,
            "staircase_voxel_mm": self.staircase_voxel_mm,
            "noise_level_mm": self.noise_level_mm,
            "fit_history": [h.to_dict() for h in self.fit.history],
            "skin_residual_mm": {"rms": round(self.skin_residual_mm[0], 4), "max": round(self.skin_residual_mm[1], 4)},
            "parameterisation": self.parameterisation.to_dict(),
            "continuity": {
                "tube": "C2 (one cubic T-spline, single interior knots; periodic in s)",
                "caps": {
                    c.end: {
                        "ring": "G1 by construction",
                        "ring_normal_angle_deg_max": round(c.ring_angle_deg[0], 6),
                        "ring_normal_angle_deg_mean": round(c.ring_angle_deg[1], 6),
                        "pole": "G1 (one tangent plane; degenerate quads meet at the pole)",
                        "pole_normal_spread_deg": round(c.pole_spread_deg, 4),
                    }
                    for c in self.caps
                },
            },
            "timings_s": {k: round(v, 3) for k, v in self.timings_s.items()},
        }


def tolerances(settings: TSplineSettings) -> FitTolerances:
    """The fit's tolerances and refinement controls from the [tspline] settings."""
    return FitTolerances(
        share_within=settings.target_share_within_mm,
        max_deviation_mm=settings.max_deviation_mm,
        rms_mm=settings.rms_mm,
        max_control_points=settings.max_control_points,
        max_rounds=settings.max_rounds,
        min_element_mm=settings.min_element_mm,
        mark_fraction=settings.mark_fraction,
        noise_factor=settings.noise_factor,
        split_anisotropy=settings.split_anisotropy,
        mark_deficit_factor=settings.mark_deficit_factor,
        noise_mark_factor=settings.rough_mark_factor,
    )


def fit_points(bone: BoneMesh, frame: AnatomicalFrame, settings: TSplineSettings) -> tuple[np.ndarray, np.ndarray]:
    """The fit's points in bone coordinates and their area weights (mm, mm^2): the mesh vertices, or
    on a coarse mesh its edge midpoints, which integrate its facets (its vertices are their corners). A dense
    mesh's working copy is simplified further for them, to triangles of about ``fit_copy_edge_mm``."""
    points, weights, _ = fit_mesh(bone, frame, settings)
    return points, weights


def fit_mesh(bone: BoneMesh, frame: AnatomicalFrame, settings: TSplineSettings
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``fit_points`` and triangles joining them (``mesh.sampling.fit_sample_mesh``)."""
    vertices, faces = bone_coordinates(bone, frame)
    if bone.working is not None:
        vertices, faces = coarser_copy(vertices, faces, settings.fit_copy_edge_mm)
    points, weights, triangles = fit_sample_mesh(vertices, faces, settings.fit_point_spacing_mm)
    return points, excluded_weights(points, weights, bone, frame), triangles


def excluded_weights(points: np.ndarray, weights: np.ndarray, bone: BoneMesh, frame: AnatomicalFrame) -> np.ndarray:
    """``weights`` zeroed at the points (bone coordinates) within ``bone.extra["excluded_mm"]`` of the faces
    centred at ``bone.extra["excluded_centres"]`` (scanner mm): a reduced fracture's surfaces, not bone."""
    centres = bone.extra.get("excluded_centres")
    if centres is None or not len(centres):
        return weights
    from scipy.spatial import cKDTree

    near = cKDTree(frame.to_bone(centres)).query(points, distance_upper_bound=bone.extra["excluded_mm"])[0]
    return np.where(np.isfinite(near), 0.0, weights)


#: A mesh triangle whose (s, t) image is larger than this many times the median triangle's spans a part of the
#: parameter domain its corners leave bare: it is sampled inside as well (issue 45).
_STRETCHED_TRIANGLE = 4.0
#: At most this many subdivisions of a stretched triangle's sides (its samples: (k + 1)(k + 2)/2 - 3).
_MAX_TRIANGLE_SPLITS = 12
#: A triangle whose corners' s differ by more than this share of the period lies about an apex ring.
_POLAR_S_SHARE = 0.125
#: ... or lies within this distance (mm of t) of an apex ring.
_RING_MARGIN_MM = 8.0
#: Crossing parameters are put right within this distance (mm of s and t) of a folded element.
_FOLD_REACH_MM = 5.0


class MeshDataHook:
    """The T-spline fit's ``data_hook`` on a mesh (issue 45, docs/guides/femur-folds.md): the fit's points
    (n, 3), their area weights (n,) and the ``triangles`` (m, 3) joining them.

    period : s's period; t_end : the t of the proximal apex ring (mm).

    The first parameters are the points' closest points on the skinned surface, which is smooth and coarse:
    it spans a deep concavity (the femur's trochanteric fossa) and its s-lines crowd where the bone comes
    near a region's axis (the anterior distal femur, the calcar below the neck). There the closest points
    of a concavity's two walls cross (a triangle's (s, t) image turns over) and whole elements of the
    domain are left with no point (a triangle's image stretches over them); a least-squares fit with a light
    thin-plate term folds in both. Before each solve, within ``_FOLD_REACH_MM`` of every element that folds
    or folded earlier in the fit: the points whose parameters cross (the corners of the turned-over triangles
    and their neighbours) are put back at parameters interpolated harmonically from the points about them,
    the points whose closest point lies on a sheet facing the other way are left out, and every stretched
    triangle is sampled inside (its facet at the same barycentric parameters), so that no part of the domain
    is bare. A fit that never folds is left alone (a small overhang whose parameters cross without folding,
    e.g. at a tibia's fibular facet, is better followed than smoothed over).
    """

    def __init__(self, points: np.ndarray, weights: np.ndarray, triangles: np.ndarray, period: float, t_end: float):
        self.points, self.weights, self.triangles, self.period, self.t_end = points, weights, triangles, period, t_end
        self.fold_boxes: list[tuple[float, float, float, float]] = []  # (s middle, s half width, t low, t high)
        n = len(points)
        i, j = triangles[:, [0, 1, 2, 1, 2, 0]].ravel(), triangles[:, [1, 2, 0, 0, 1, 2]].ravel()
        self.adjacency = sp.csr_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
        self.adjacency.data[:] = 1.0
        tri = points[triangles]
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.areas = 0.5 * np.linalg.norm(cross, axis=1)
        self.normals = np.zeros_like(points)
        for k in range(3):
            np.add.at(self.normals, triangles[:, k], cross)

    def _near_folds(self, ts: TSpline, s: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(n,) bool: points whose parameters lie within ``_FOLD_REACH_MM`` of an element that folds
        (``element_turns_deg``) in ``ts`` or folded in an earlier solve of the same fit: crossing parameters
        elsewhere (a small overhang the surface follows) are left as they are."""
        ext = ts.extraction
        for e in np.flatnonzero(element_turns_deg(ts) > FOLD_TURN_DEG):
            (s0, s1), (t0, t1) = ext.s_bounds[e], ext.t_bounds[e]
            self.fold_boxes.append((0.5 * (s0 + s1), 0.5 * (s1 - s0) + _FOLD_REACH_MM, t0 - _FOLD_REACH_MM,
                                    t1 + _FOLD_REACH_MM))
        near = np.zeros(len(s), bool)
        for mid, half, low, high in self.fold_boxes:
            ds = np.abs((s - mid + 0.5 * self.period) % self.period - 0.5 * self.period)
            near |= (ds <= half) & (t >= low) & (t <= high)
        return near

    def _unwrapped(self, s: np.ndarray, graph: sp.csr_matrix) -> np.ndarray:
        """s (periodic) unwrapped along the edges of ``graph``: each vertex differs from the one it is reached
        from by less than half a period (breadth first from one vertex of each connected patch)."""
        out = s.copy()
        done = np.zeros(len(s), bool)
        for root in range(len(s)):
            if done[root]:
                continue
            order, parent = breadth_first_order(graph, root, directed=False)
            for v in order[1:]:
                step = (s[v] - s[parent[v]] + 0.5 * self.period) % self.period - 0.5 * self.period
                out[v] = out[parent[v]] + step
            done[order] = True
        return out

    def _harmonic(self, s: np.ndarray, t: np.ndarray, free: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The ``free`` points with parameters interpolated harmonically (uniform weights) from the
        points about them, as extra data: (points, s, t, weights)."""
        adj = self.adjacency
        near = free | (adj @ free.astype(float) > 0)
        sub = adj[near][:, near]
        near_idx = np.flatnonzero(near)
        s_near = self._unwrapped(s[near_idx], sub)
        inner, rim = np.flatnonzero(free[near_idx]), np.flatnonzero(~free[near_idx])
        lap = (sp.diags(np.asarray(sub.sum(axis=1)).ravel()) - sub).tocsr()
        rows = lap[inner]
        rhs = -(rows[:, rim] @ np.column_stack([s_near[rim], t[near_idx][rim]]))
        sol = np.asarray(spsolve(rows[:, inner].tocsc(), rhs)).reshape(-1, 2)
        idx = near_idx[inner]
        return self.points[idx], sol[:, 0] % self.period, sol[:, 1], self.weights[idx]

    def __call__(self, ts: TSpline, s: np.ndarray, t: np.ndarray
                 ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None]:
        near = self._near_folds(ts, s, t)
        if not near.any():
            return near, None
        tri = self.triangles
        ds = s[tri[:, 1:]] - s[tri[:, :1]]
        ds = (ds + 0.5 * self.period) % self.period - 0.5 * self.period
        dt = t[tri[:, 1:]] - t[tri[:, :1]]
        signed = (ds[:, 0] * dt[:, 1] - ds[:, 1] * dt[:, 0]) / 2
        # about an apex ring the closest points crowd onto the ring and a triangle may span much of the period
        # in s: its image is no triangle there, and it is never judged
        polar = np.max(np.abs(np.column_stack([ds, ds[:, 0] - ds[:, 1]])), axis=1) > _POLAR_S_SHARE * self.period
        polar |= ((t[tri] < _RING_MARGIN_MM) | (t[tri] > self.t_end - _RING_MARGIN_MM)).any(axis=1)
        turned = (signed * np.sign(np.sum(signed)) < 0) & ~polar
        left_out = np.zeros(len(self.points), bool)
        left_out[tri[turned].ravel()] = True
        left_out[tri[left_out[tri].any(axis=1)].ravel()] = True  # and their neighbours
        left_out &= near
        crossing = int(left_out.sum())
        sample = ts.evaluate(s, t, order=1)
        facing = np.einsum("ij,ij->i", np.cross(sample.derivatives[0], sample.derivatives[1]), self.normals) < 0
        facing &= near
        if crossing:
            extra_crossing = self._harmonic(s, t, left_out)
        left_out |= facing
        area = np.abs(signed)
        ratio = area / np.median(area)
        stretched = np.flatnonzero((ratio > _STRETCHED_TRIANGLE) & ~polar & ~left_out[tri].any(axis=1)
                                   & near[tri].any(axis=1))
        splits = np.minimum(np.ceil(np.sqrt(ratio[stretched])), _MAX_TRIANGLE_SPLITS).astype(int)
        parts = []
        for k in np.unique(splits):
            i, j = np.meshgrid(np.arange(k + 1), np.arange(k + 1), indexing="ij")
            corner = ((i == 0) & (j == 0)) | ((i == k) & (j == 0)) | ((i == 0) & (j == k))
            inner = (i + j <= k) & ~corner
            bary = np.column_stack([k - i[inner] - j[inner], i[inner], j[inner]]) / k  # (q, 3), corners dropped
            sel = stretched[splits == k]
            corners = self.points[tri[sel]]  # (r, 3, 3)
            p = np.einsum("qc,rcx->rqx", bary, corners).reshape(-1, 3)
            ps = ((s[tri[sel, 0]][:, None] + ds[sel] @ bary[:, 1:].T) % self.period).ravel()  # (r, q)
            pt = (t[tri[sel, 0]][:, None] + dt[sel] @ bary[:, 1:].T).ravel()
            pw = np.repeat(self.areas[sel] / len(bary), len(bary))
            parts.append((p, ps, pt, pw))
        log.debug("fit data: %d points left out (%d whose parameters cross, %d facing the other way), %d "
                  "stretched triangles sampled inside", int(left_out.sum()), crossing, int(facing.sum()),
                  len(stretched))
        if crossing:
            parts.append(extra_crossing)
        if not parts:
            return left_out, None
        return left_out, tuple(np.concatenate([q[k] for q in parts]) for k in range(4))  # type: ignore[return-value]


@dataclass(frozen=True)
class MeshNoise:
    """The mesh's noise at the T-spline fit's points: local_mm (n,) at every fit point (mm), level_mm the
    mesh's noise level (mm, ``noise_level_mm``)."""

    local_mm: np.ndarray
    level_mm: float


def mesh_noise(bone: BoneMesh, frame: AnatomicalFrame, settings: TSplineSettings) -> MeshNoise:
    """The mesh's noise: the local noise at every fit point (the same spacing on every mesh, so the same
    scale; a staircase (voxel-mask mesh), whose lattice shows in scanner coordinates, has at least its
    steps'), and its noise level (settings ``noise_level_radius_mm``, ``noise_level_quantile``)."""
    vertices, weights = fit_points(bone, frame, settings)
    local = local_noise_mm(vertices, neighbours=settings.noise_neighbours, voxel_mm=bone.voxel_step_mm)
    return MeshNoise(local, noise_level_mm(vertices, weights, radius_mm=settings.noise_level_radius_mm,
                                           quantile=settings.noise_level_quantile,
                                           stride=settings.noise_level_stride))


def hole_masks(vertices: np.ndarray, frame: AnatomicalFrame, radius_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Mesh vertices inside the distal and the proximal apex hole (bone coordinates): within ``radius_mm`` of
    the mechanical axis below the distal boundary, of the local proximal axis above the proximal boundary."""
    distal = (vertices[:, 2] < frame.distal_boundary_mm) & (np.linalg.norm(vertices[:, :2], axis=1) < radius_mm)
    a, b = frame.to_bone(frame.local_proximal_axis)
    d = (a - b) / np.linalg.norm(a - b)
    rel = vertices - a
    off = rel - np.outer(rel @ d, d)
    proximal = (vertices[:, 2] > frame.proximal_boundary_mm) & (np.linalg.norm(off, axis=1) < radius_mm)
    return distal, proximal


def ring_constraints(
    contours: ContourSet, par: Parameterisation, radius_mm: float, *, count: int = 180, band_mm: float = 5.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points of the two apex rings with fixed parameters (t = 0 and t = t_end).

    The ring of an end is where the bone meets the cylinder of the apex-hole
    radius about that end's axis: the half-plane curves start on it; between
    them its height along the axis is interpolated (periodic, linear in the
    angle). Each point weighs as a strip ``band_mm`` wide, so the tube's
    boundary rows, which no mesh point pins down, follow the hole's edge
    instead of wrinkling. Returns (points (2 count, 3), s, t, weights).
    """
    theta = np.linspace(0.0, 360.0, count, endpoint=False)
    out_p, out_s, out_t = [], [], []
    a, b = par.local_axis
    local = (a - b) / np.linalg.norm(a - b)
    for curves, origin, axis, t_value in (
        (contours.distal, np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.0),
        (contours.proximal, a, local, par.t_end),
    ):
        e1 = np.array([1.0, 0.0, 0.0]) - axis[0] * axis
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(axis, e1)
        angles = np.array([c.angle % 360.0 for c in curves])
        heights = np.array([(c.curve(np.array([0.0]))[0] - origin) @ axis for c in curves])
        h = np.interp(theta, angles, heights, period=360.0)
        rad = np.radians(theta)
        ring = origin + radius_mm * (np.cos(rad)[:, None] * e1 + np.sin(rad)[:, None] * e2) + h[:, None] * axis
        out_p.append(ring)
        out_s.append(theta / 360.0 * par.s_period)
        out_t.append(np.full(count, t_value))
    weight = 2 * np.pi * radius_mm / count * band_mm
    return np.vstack(out_p), np.concatenate(out_s), np.concatenate(out_t), np.full(2 * count, weight)


def build_tspline_model(
    bone: BoneMesh,
    frame: AnatomicalFrame,
    contours: ContourSet,
    *,
    settings: TSplineSettings,
    apex_hole_radius_mm: float,
    noise: MeshNoise | None = None,
    progress: Callable[[int, FitStats], None] | None = None,
) -> TSplineModel:
    """Skin, fit, refine, cap and convert: the T-spline model of a tibia.

    settings : the [tspline] settings (``compare_tensor_product`` fits the
        tensor-product comparison surface too; it about doubles the time).
    apex_hole_radius_mm : the contour curves' apex hole radius.
    noise : ``mesh_noise`` of the same bone, frame and settings, when the
        caller measured it already (the runner does, on the second core).
    progress : called with (round, FitStats) after each round of the fit (the runner's progress bar).
    Raises FitError when a stage cannot produce a usable surface, KernelError
    when OpenCascade cannot make a valid closed solid of it.
    """
    st = settings
    tol = tolerances(st)
    fair, fit_fair = st.fairness_weight, st.fit_fairness_weight
    timings: dict[str, float] = {}
    clock = time.perf_counter()

    vertices, weights, triangles = fit_mesh(bone, frame, st)
    par = parameterisation(contours)
    radius = apex_hole_radius_mm
    hole_d, hole_p = hole_masks(vertices, frame, radius)
    rings = ring_constraints(contours, par, radius)
    keep = ~(hole_d | hole_p) & (weights > 0)
    pts, w = vertices[keep], weights[keep]
    index = np.cumsum(keep) - 1
    # the triangles joining the kept points, for the fit's data hook (MeshDataHook); on a rough mesh, whose noise
    # turns triangles over everywhere, it does more harm than good (ICL MRI femur: 13 -> 27 folded elements)
    joined = index[triangles[keep[triangles].all(axis=1)]]

    mesh = initial_mesh(par, s_intervals=st.initial_s_intervals, t_spacing_mm=st.initial_t_spacing_mm,
                        apex_rows=st.apex_rows)
    ts0, _, residual = skin(contours, par, mesh, fairness=fair)
    skin_res = (float(np.sqrt(np.mean(residual**2))), float(residual.max()))
    timings["skin"] = time.perf_counter() - clock

    clock = time.perf_counter()
    voxel = bone.voxel_step_mm
    if voxel:
        log.info("the mesh is a %.2f mm voxel staircase (vertices on a lattice): its steps count as noise", voxel)
    s0, t0, _ = initial_parameters(ts0, pts)
    if noise is None:
        noise = mesh_noise(bone, frame, st)
    local = noise.local_mm[keep]
    level = noise.level_mm
    # a voxel staircase has its own noise floor and stop (its steps, ``local_noise_mm(voxel_mm=...)``)
    rough = level if level >= st.rough_noise_level_mm and not voxel else 0.0
    if rough:
        log.info("the mesh is rough (noise level %.3f mm): the fit stops at its noise", level)
    fit = fit_adaptive(ts0, pts, w, s=s0, t=t0, tolerances=tol, fairness=fit_fair, mode="local",
                       constraints=rings, noise=local, noise_level=rough, progress=progress,
                       data_hook=None if rough else MeshDataHook(pts, w, joined, par.s_period, par.t_end))
    timings["fit"] = time.perf_counter() - clock
    if not fit.converged:
        staircase = f"; the mesh is a {voxel:.2f} mm voxel staircase" if voxel else ""
        log.warning("T-spline fit stopped before the tolerances held: %s (%s)%s", fit.stopped, fit.stats.to_dict(),
                    staircase)
    if fit.folded_elements:
        log.warning("the T-spline folds in %d Bezier elements (a sheet turned back on itself: the model does "
                    "not meet its tolerances)", fit.folded_elements)

    tp_fit = None
    if st.compare_tensor_product:
        clock = time.perf_counter()
        grid = initial_mesh(par, s_intervals=st.initial_s_intervals, t_spacing_mm=st.initial_t_spacing_mm,
                            apex_rows=0)
        tp0, _, _ = skin(contours, par, grid, fairness=fair)
        s1, t1, _ = initial_parameters(tp0, pts)
        tp_fit = fit_adaptive(tp0, pts, w, s=s1, t=t1, tolerances=tol, fairness=fit_fair, mode="global",
                              constraints=rings, noise=local, noise_level=rough,
                              data_hook=None if rough else MeshDataHook(pts, w, joined, par.s_period, par.t_end))
        timings["tensor_product"] = time.perf_counter() - clock

    clock = time.perf_counter()
    tube = fit.tspline
    caps = apex_caps(tube, par, vertices[hole_d], vertices[hole_p])
    timings["caps"] = time.perf_counter() - clock
    clock = time.perf_counter()
    shape, face_names = occ_shape(tube, caps, par, frame, settings=st)
    timings["occ"] = time.perf_counter() - clock
    return TSplineModel(
        tspline=tube,
        caps=caps,
        parameterisation=par,
        fit=fit,
        skin_residual_mm=skin_res,
        tensor_product_control_points=None if tp_fit is None else tp_fit.tspline.n_control,
        tensor_product_converged=None if tp_fit is None else tp_fit.converged,
        tensor_product_fit=tp_fit,
        shape=shape,
        face_names=tuple(face_names),
        frame=frame,
        staircase_voxel_mm=round(voxel, 4),
        noise_level_mm=round(level, 4),
        timings_s=timings,
    )


def apex_caps(tube: TSpline, par: Parameterisation, distal_points: np.ndarray,
              proximal_points: np.ndarray) -> tuple[ApexCap, ApexCap]:
    """The caps of the tube's two apex holes (bone coordinates, mm): the distal one facing down the
    z axis, the proximal one along the plateau's local axis; *_points: (m, 3) mesh points inside each hole."""
    local_dir = par.local_axis[0] - par.local_axis[1]
    return (build_cap(tube, "distal", distal_points, np.array([0.0, 0.0, -1.0])),
            build_cap(tube, "proximal", proximal_points, local_dir / np.linalg.norm(local_dir)))


class ScannerMap(Protocol):
    """Maps bone coordinates to the output's (an AnatomicalFrame; the identity for a shape with no scan)."""

    def to_scanner(self, points: np.ndarray) -> np.ndarray: ...


def to_scanner(ts: TSpline, frame: ScannerMap) -> TSpline:
    """The same T-spline mapped to scanner coordinates (an affine map of the control points: exact)."""
    return ts.with_control_points(frame.to_scanner(ts.control_points), ts.weights)


FACE_LAYOUTS = ("tube", "panels", "blocks", "elements")


def occ_shape(tube: TSpline, caps: tuple[ApexCap, ApexCap], par: Parameterisation, frame: ScannerMap, *,
              settings: TSplineSettings) -> tuple[object, list[tuple[str, object]]]:
    """The tube's and the caps' faces (scanner coordinates), sewn into a closed, valid solid with outward faces.

    settings.face_layout : "tube": the tube as one B-spline face named "tube", exactly (its
    tensor-product form on all its knot lines,
    :func:`~bonecad.splines.tspline.tensor.tensor_product_form`), and each cap as
    one face; "panels": one B-spline face per rectangle of the tube's panel plan
    (:func:`~bonecad.splines.tspline.tensor.panel_plan`, cut at the region
    boundaries; exactly the same surface, the fewest poles); "blocks": one B-spline
    face per tensor-product block of Bezier elements (exactly the same surface);
    "elements": one Bezier face per element. Tube faces of "panels", "blocks" and
    "elements" are named by the region ("distal", "shaft", "proximal") that holds
    the middle of their t-range. Cap faces are "distal_apex_cap" /
    "proximal_apex_cap" (one per block of the cap's elements but with "tube").
    Returns (solid, [(name, face)]).
    """
    from bonecad.occ.brep import is_valid, named_solid
    from bonecad.occ.tspline import bezier_faces, bspline_face, merged_faces, panel_faces
    from bonecad.splines.tspline.tensor import panel_plan, tensor_product_form

    layout = settings.face_layout
    if layout not in FACE_LAYOUTS:
        raise ValueError(f"face layout must be one of {FACE_LAYOUTS}, got {layout!r}")

    def faces_of(ts: TSpline, edge_per_element: bool = False) -> tuple[list, np.ndarray]:
        """Faces of a patch and the t in the middle of each (parameters of ``ts``)."""
        ext = ts.extraction
        scanner = to_scanner(ts, frame)
        if layout == "elements":
            return bezier_faces(scanner), ext.t_bounds.mean(axis=1)
        pairs = merged_faces(scanner, edge_per_element=edge_per_element)
        return [f for f, _ in pairs], np.array([ext.t_bounds[b].mean() for _, b in pairs])

    def tube_faces(edge_per_element: bool) -> tuple[list, np.ndarray]:
        if layout != "panels":
            return faces_of(tube, edge_per_element)
        plan = panel_plan(tube, t_cuts=(par.t_distal, par.t_proximal), face_cost=settings.panel_face_cost,
                          t_step=settings.panel_t_step)
        return (panel_faces(to_scanner(tube, frame), plan, edge_per_span=edge_per_element),
                np.array([0.5 * (t0 + t1) for _, _, t0, t1 in plan]))

    if layout == "tube":
        cap_faces = [(f"{cap.end}_apex_cap", bspline_face(to_scanner(cap.tspline, frame))) for cap in caps]
    else:
        cap_faces = [(f"{cap.end}_apex_cap", face) for cap in caps for face in faces_of(cap.tspline)[0]]
    problems = []
    # A side of a merged tube face that curls back to within the sewing tolerance of itself (a
    # crumpled surface of tiny elements) stays unsewn; bounded by one edge per element side, it
    # sews (merged_faces: edge_per_element). The lean faces first, as they sew ~4x faster.
    for edge_per_element in (False, True) if layout in ("blocks", "panels") else (False,):
        if layout == "tube":
            named = [("tube", bspline_face(to_scanner(tensor_product_form(tube), frame))), *cap_faces]
        else:
            faces, t_mid = tube_faces(edge_per_element)
            regions = np.where(t_mid < par.t_distal, "distal", np.where(t_mid > par.t_proximal, "proximal", "shaft"))
            named = list(zip(regions.tolist(), faces)) + cap_faces
        bounds = "one edge per element side, " if edge_per_element else ""
        # Neighbouring Bezier edges agree to rounding; a T-junction lying a few
        # micrometres from an element corner can still leave a pair unsewn at the
        # finest tolerance, so widen it (up to 10 um) until the solid closes.
        for tol in _SEWING_TOLERANCES_MM:
            try:
                solid, face_names = named_solid(named, tolerance_mm=tol)
            except KernelError as exc:
                problems.append(f"{bounds}{tol} mm: {exc}")
                continue
            if is_valid(solid):
                if edge_per_element:
                    log.info("the T-spline's faces sewn bounded by one edge per element side (%s)", "; ".join(problems))
                return solid, face_names
            problems.append(f"{bounds}{tol} mm: not valid (BRepCheck_Analyzer)")
    raise KernelError(f"the T-spline faces ({len(named)}) do not sew into a valid closed solid: " + "; ".join(problems))
