"""Least-squares fitting of cubic T-splines to points, with parameter correction
and error-driven refinement (TSPLINE.md, "Fitting").

With weights 1 a T-spline is linear in its control points, so fitting is a
sparse linear least-squares problem (each row holds at most 16 non-zeros):

    min_P  sum_k w_k |S(s_k, t_k) - x_k|^2 / sum_k w_k  +  lambda E_fair(P),
    E_fair = integral |S_ss|^2 + 2 |S_st|^2 + |S_tt|^2 ds dt  (thin-plate energy),

solved through the normal equations with a sparse LU (the normal matrix is
symmetric positive definite; one factorisation serves the three coordinates).
Parameters are corrected by projecting every point onto the surface (Newton on
the squared distance; Hoschek 1988, "Intrinsic parametrization for
approximation"; Piegl & Tiller, The NURBS Book, sec. 9.4), and the surface is
refined where the error stays above the tolerance:

- ``mode="local"``: the failing Bezier elements are halved, across the
  direction their residual varies along (or both; one direction for each
  cluster of neighbouring failing elements), by exact,
  analysis-suitable local refinement (Scott, Li, Sederberg, Hughes 2012);
- ``mode="global"``: the same knot lines, but whole, are inserted, which
  keeps a tensor product (the comparison surface).

Everything here is numpy/scipy on the parameter domain of the T-spline; it
knows nothing of bones.
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from bonecad.splines.tspline import BezierExtraction, KnotSegment, TSpline, insert_segments, refine_elements
from bonecad.splines.basis import bernstein3
from bonecad.splines.folds import FOLD_SAMPLES, FOLD_TURN_DEG, element_grid, largest_turn_deg
from bonecad.splines.lsq import normal_equations, solve_spd

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FitTolerances:
    """When a fit is good enough, and how hard to try (the models take them from their settings).

    share_within : (share, mm): this share of the (weighted) points lies within mm.
    max_deviation_mm : no point beyond this.
    rms_mm : weighted RMS distance at most this.
    max_control_points : refinement budget (stop, and say so, when the next round would pass it).
    max_rounds : refinement rounds at most.
    min_element_mm : elements smaller than this (parameter units; mm along s and t
        for the bone's arc-length parameterisation) are not refined further.
    mark_fraction : each round refines the fewest elements that hold this
        fraction of the point weight beyond the tolerance (Doerfler marking),
        and every element with a point beyond ``max_deviation_mm``.
    mark_deficit_factor : near the target, mark instead only this many times
        the point weight the share target still misses (no last-round overshoot).
    split_anisotropy : a marked element is halved across one direction only
        when the part of its residual that varies along that direction (between
        four bins of the local coordinate) is this many times the part varying
        along the other, both summed over its cluster of edge-adjacent marked
        elements (one direction per cluster); else it is split into four (inf:
        always four).
    noise_factor : noise-aware stopping (with ``fit_adaptive(noise=...)``): a
        point whose distance is within this many times the local noise level
        of the data is fitted as well as the data allow, and does not ask for
        refinement (an MRI slice staircase is not followed). Once the share
        holds with those points counted as fitted, only points beyond
        ``max_deviation_mm`` ask for more, and where they lie in elements at
        the size limit the fit stops at the noise (and says so).
    noise_mark_factor : on rough data (``fit_adaptive(noise_level=...)``) each round marks the fewest
        elements holding this many times the squared residual the fit still has above the noise level
        (mm^2 x area; see ``_marked_elements``): small steps towards the noise stop, which ends the fit
        at the first round whose RMS residual is at the noise level.
    """

    share_within: tuple[float, float]
    max_deviation_mm: float
    rms_mm: float
    max_control_points: int
    max_rounds: int
    min_element_mm: float
    mark_fraction: float
    noise_factor: float
    split_anisotropy: float
    mark_deficit_factor: float
    noise_mark_factor: float = 0.6


@dataclass(frozen=True)
class FitStats:
    """Distances of the fitted points to the surface (after projection).

    share_within : weighted share within the tolerance distance; max_mm, rms_mm : weighted.
    """

    control_points: int
    elements: int
    share_within: float
    max_mm: float
    rms_mm: float

    def meets(self, tol: FitTolerances) -> bool:
        return (
            self.share_within >= tol.share_within[0]
            and self.max_mm <= tol.max_deviation_mm
            and self.rms_mm <= tol.rms_mm
        )

    def to_dict(self) -> dict:
        return {
            "control_points": self.control_points,
            "elements": self.elements,
            "share_within": round(self.share_within, 5),
            "max_mm": round(self.max_mm, 4),
            "rms_mm": round(self.rms_mm, 4),
        }


@dataclass(frozen=True)
class FitResult:
    """An adaptive fit: the surface, the final parameters of the points, and the history.

    s, t : (n,) parameters of the points on the final surface; distance_mm : (n,).
    converged : the tolerances hold; stopped : why refinement stopped.
    folded_elements : Bezier elements of the surface whose normal reverses inside them (0 for a fit
        without folds).
    """

    tspline: TSpline
    s: np.ndarray
    t: np.ndarray
    distance_mm: np.ndarray
    stats: FitStats
    history: list[FitStats] = field(default_factory=list)
    converged: bool = False
    stopped: str = ""
    folded_elements: int = 0


# ------------------------------------------------------------------ projection
def _wrap_clamp(ts: TSpline, s: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mesh = ts.mesh
    lo, hi = mesh.s_range
    if mesh.s_period is not None:
        s = lo + np.mod(s - lo, mesh.s_period)
    else:
        s = np.clip(s, lo, hi)
    return s, np.clip(t, *mesh.t_range)


def project_points(
    ts: TSpline, points: np.ndarray, s: np.ndarray, t: np.ndarray, *, iterations: int = 6
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest points by Newton's method on |S(s, t) - x|^2 from a starting guess.

    points : (n, 3) mm; s, t : (n,) starting parameters. Steps are damped so the
    distance never grows; parameters stay in the domain (s wraps, t clamps).
    Returns (s, t, distance (n,) mm).
    """
    points = np.asarray(points, dtype=np.float64)
    s, t = _wrap_clamp(ts, np.asarray(s, dtype=np.float64).copy(), np.asarray(t, dtype=np.float64).copy())
    cur = ts.evaluate(s, t, order=2)
    r = cur.points - points
    dist2 = np.einsum("ij,ij->i", r, r)
    for it in range(iterations):
        su, tv = cur.du, cur.dv
        dss, dst, dtt = cur.duu, cur.duv, cur.dvv
        g0 = np.einsum("ij,ij->i", su, r)
        g1 = np.einsum("ij,ij->i", tv, r)
        a = np.einsum("ij,ij->i", su, su) + np.einsum("ij,ij->i", dss, r)
        b = np.einsum("ij,ij->i", su, tv) + np.einsum("ij,ij->i", dst, r)
        c = np.einsum("ij,ij->i", tv, tv) + np.einsum("ij,ij->i", dtt, r)
        det = a * c - b * b
        ok = (a > 0) & (det > 1e-12 * np.maximum(a * c, 1e-300))
        # Newton where the Hessian is positive definite, else a gradient step (Gauss-Newton diagonal)
        gn_a = np.maximum(np.einsum("ij,ij->i", su, su), 1e-300)
        gn_c = np.maximum(np.einsum("ij,ij->i", tv, tv), 1e-300)
        ds_ = np.where(ok, -(c * g0 - b * g1) / np.where(ok, det, 1.0), -g0 / gn_a)
        dt_ = np.where(ok, -(a * g1 - b * g0) / np.where(ok, det, 1.0), -g1 / gn_c)
        step = 1.0
        active = np.ones(len(s), dtype=bool)
        new_s, new_t = s.copy(), t.copy()
        for _halving in range(4):
            cand_s, cand_t = _wrap_clamp(ts, s + step * ds_, t + step * dt_)
            idx = np.flatnonzero(active)
            if idx.size == 0:
                break
            p = ts.evaluate(cand_s[idx], cand_t[idx]).points - points[idx]
            d2 = np.einsum("ij,ij->i", p, p)
            better = d2 <= dist2[idx]
            new_s[idx[better]] = cand_s[idx[better]]
            new_t[idx[better]] = cand_t[idx[better]]
            dist2[idx[better]] = d2[better]
            active[idx[better]] = False
            step *= 0.5
        moved = np.abs(new_s - s).max(initial=0.0) + np.abs(new_t - t).max(initial=0.0)
        s, t = new_s, new_t
        if moved < 1e-10 or it == iterations - 1:
            break  # dist2 already holds the distances at the accepted steps
        cur = ts.evaluate(s, t, order=2)
        r = cur.points - points
    return s, t, np.sqrt(dist2)


def initial_parameters(
    ts: TSpline, points: np.ndarray, *, grid: tuple[int, int] = (256, 1024), iterations: int = 6
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest-point parameters of points on a surface with no prior guess.

    The surface is sampled on a ``grid`` (s, t) of parameter values; each point
    starts at its nearest sample (KD-tree) and is then projected by Newton.
    Returns (s, t, distance (n,) mm).
    """
    (s0, s1), (t0, t1) = ts.mesh.s_range, ts.mesh.t_range
    ns, nt = grid
    gs = np.linspace(s0, s1, ns, endpoint=not ts.mesh.periodic)
    gt = np.linspace(t0, t1, nt)
    ss, tt = np.meshgrid(gs, gt, indexing="ij")
    samples = ts.evaluate(ss.ravel(), tt.ravel()).points
    _, idx = cKDTree(samples).query(np.asarray(points, dtype=np.float64))
    return project_points(ts, points, ss.ravel()[idx], tt.ravel()[idx], iterations=iterations)


def local_noise_mm(points: np.ndarray, *, neighbours: int = 24, voxel_mm: float = 0.0,
                   at: np.ndarray | None = None) -> np.ndarray:
    """(n,) mm: how far the data scatter about a smooth surface near each point (``at``: only near these
    indices of ``points``, their neighbours still among all points; None: every point).

    For every point, a quadric height field z = a + bx + cy + dx^2 + exy + fy^2
    is fitted (least squares) to its ``neighbours`` nearest points in the
    frame of their principal axes; the RMS of its residuals is the local noise.
    On a smooth, finely sampled surface it is far below any tolerance; on a
    staircase of MRI slices it is the steps' scatter, and on a crease sharper
    than the sampling it is the crease's mismatch: in both, no surface that
    is smooth at the mesh's resolution comes closer.

    voxel_mm : the voxel size of a staircase mesh (``voxel_step_mm``; 0: none).
    A quadric through a vertex's nearest neighbours follows one or two voxel
    steps and underrates the staircase, so the noise is then at least
    voxel_mm / sqrt(12), the RMS distance of a staircase of that step from
    the smooth surface through it (a uniform error over one step).
    """
    points = np.asarray(points, dtype=np.float64)
    centres = points if at is None else points[at]
    k = min(neighbours, len(points))
    if k < 10:
        return np.zeros(len(centres))
    _, idx = cKDTree(points).query(centres, k=k)
    out = np.empty(len(centres))
    for lo in range(0, len(centres), 1 << 14):
        nb = points[idx[lo : lo + (1 << 14)]]  # (m, k, 3)
        q = nb - nb.mean(axis=1, keepdims=True)
        # batched matmuls throughout (several times faster than the equivalent einsums), on arrays whose
        # last axis runs over the neighbours: every coordinate and quadric term a contiguous row (stacking
        # the terms along a last axis of 6 took 2 of the 4 s at 61 k points and 180 neighbours)
        _, vec = np.linalg.eigh(q.transpose(0, 2, 1) @ q)  # ascending: vec[..., 0] = normal
        local = vec.transpose(0, 2, 1) @ q.transpose(0, 2, 1)  # (m, 3, k): height, then the two tangents
        z, x, y = local[:, 0], local[:, 1], local[:, 2]
        design = np.empty((len(nb), 6, nb.shape[1]))  # (m, 6, k): 1, x, y, x^2, xy, y^2
        design[:, 0] = 1.0
        design[:, 1], design[:, 2] = x, y
        np.multiply(x, x, out=design[:, 3])
        np.multiply(x, y, out=design[:, 4])
        np.multiply(y, y, out=design[:, 5])
        ata = design @ design.transpose(0, 2, 1) + 1e-9 * np.eye(6)
        coef = np.linalg.solve(ata, design @ z[..., None])  # (m, 6, 1)
        res = z - (coef.transpose(0, 2, 1) @ design)[:, 0]
        out[lo : lo + len(nb)] = np.sqrt(np.mean(res**2, axis=1))
    return np.maximum(out, voxel_mm / np.sqrt(12.0))


def noise_level_mm(points: np.ndarray, weights: np.ndarray, *, radius_mm: float, quantile: float,
                   stride: int = 1) -> float:
    """The data's noise level (mm): a low quantile over the points of their scatter about a quadric fitted
    over a neighbourhood of ``radius_mm`` (``local_noise_mm`` with as many neighbours as cover
    pi radius^2 of surface; weights: (n,) area each point stands for, mm^2). A low quantile, as
    measurement noise covers the whole surface and features of shape only part of it: the smoothest
    part of the surface shows the noise. stride : the quantile over every stride-th point (the
    neighbourhoods overlap: a sample of them gives the quantile, at a stride-th of the cost)."""
    area = float(np.sum(weights)) / len(points)
    scatter = local_noise_mm(points, neighbours=int(np.pi * radius_mm**2 / area),
                             at=np.arange(0, len(points), stride))
    return float(np.quantile(scatter, quantile))


def voxel_step_mm(points: np.ndarray, *, max_distinct: float = 0.05) -> float:
    """The voxel size of a staircase mesh (0.0 when the mesh is not one).

    A mesh made from a voxel mask without sub-voxel interpolation has its
    vertices on a lattice: along at least two axes (of the scanner frame,
    where the voxels are) the coordinates take few distinct values (at most
    ``max_distinct`` of the vertex count). Its vertices then sit at voxel
    corners or edge midpoints, so the voxel is twice the commonest spacing
    of the distinct values; the largest over the lattice axes is returned.
    """
    points = np.asarray(points, dtype=np.float64)
    steps = []
    for ax in range(points.shape[1]):
        u = np.unique(np.round(points[:, ax], 6))
        if len(u) < 3 or len(u) > max_distinct * len(points):
            continue
        d = np.diff(u)
        steps.append(2.0 * float(np.median(d[d > 1e-6])))
    return max(steps) if len(steps) >= 2 else 0.0


# --------------------------------------------------------------- least squares
def _bernstein_moments() -> np.ndarray:
    """(3, 4, 4): integrals over [0, 1] of products of the cubic Bernstein
    polynomials' derivatives of order 0, 1, 2 (4-point Gauss: exact)."""
    g, gw = np.polynomial.legendre.leggauss(4)
    b = bernstein3(0.5 * (g + 1.0), 2)
    return np.einsum("q,kqi,kqj->kij", 0.5 * gw, b, b)


_MOMENTS = _bernstein_moments()


def _block_diagonal(blocks: np.ndarray) -> sp.csr_matrix:
    """(n_e, 16, 16) element blocks -> csr (16 n_e, 16 n_e), the layout of the extraction operator's rows."""
    n = len(blocks)
    idx = np.arange(16 * n).reshape(n, 1, 16)
    cols = np.broadcast_to(idx, (n, 16, 16)).ravel()
    return sp.csr_matrix((blocks.ravel(), cols, np.arange(0, 256 * n + 1, 16)), shape=(16 * n, 16 * n))


def fairness_blocks(ts: TSpline) -> np.ndarray:
    """(n_e, 16, 16) thin-plate energy of each Bezier element in its Bernstein coefficients.

    E_fair = integral of |S_ss|^2 + 2 |S_st|^2 + |S_tt|^2 over the parameter
    domain (mm^2, exact for the bicubic elements), = sum_e q_e^T K_e q_e for
    Bezier points q_e = C_e^T P. Integrated, not averaged: against the mean
    squared distance of the data term, a fixed weight then smooths a large
    domain as firmly as a small one per unit of parameter area.
    """
    ext = ts.extraction
    hs = np.diff(ext.s_bounds, axis=1)[:, 0]
    ht = np.diff(ext.t_bounds, axis=1)[:, 0]
    m, d1, d2 = _MOMENTS
    return ((ht / hs**3)[:, None, None] * np.kron(d2, m) + (2.0 / (hs * ht))[:, None, None] * np.kron(d1, d1)
            + (hs / ht**3)[:, None, None] * np.kron(m, d2))


def solve_control_points(
    ts: TSpline,
    s: np.ndarray,
    t: np.ndarray,
    points: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    fairness: float = 1e-4,
) -> TSpline:
    """Least-squares control points for points at given parameters (same T-mesh).

    ts : a polynomial T-spline (weights 1 up to rounding), the mesh to fit on.
    points : (n, 3) mm; weights : (n,) >= 0 (None: equal).
    fairness : weight lambda of the thin-plate term (integral over the
        parameter domain) against the mean squared distance; it keeps the
        surface from folding where no datum holds it.
    The normal equations are assembled per Bezier element (Bernstein Gram
    matrix of the element's points plus lambda times its thin-plate block)
    and mapped to control points by the extraction operator C: N = C^T (G + lambda K) C.
    Returns a polynomial T-spline on the same mesh.
    """
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    if points.shape != (n, 3) or np.shape(s) != (n,) or np.shape(t) != (n,):
        raise ValueError(f"points, s, t: expected (n, 3), (n,), (n,), got {points.shape}, {np.shape(s)}, {np.shape(t)}")
    if np.abs(ts.weights - 1.0).max() > 1e-9:
        raise ValueError("solve_control_points: expected a polynomial T-spline (weights 1)")
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    ext = ts.extraction
    elem, u, v = ext.locate(s, t)
    rows = (bernstein3(u)[0][:, :, None] * bernstein3(v)[0][:, None, :]).reshape(n, 16)
    bern = sp.csr_matrix((rows.ravel(), (16 * elem[:, None] + np.arange(16)).ravel(), np.arange(0, 16 * n + 1, 16)),
                         shape=(n, 16 * ext.n_elements))
    fair = fairness * _block_diagonal(fairness_blocks(ts)) if fairness > 0 else None
    inner, rhs = normal_equations(bern, w, points, fair)
    op = ext.operator
    # tiny Tikhonov term: control points no datum or fairness reaches stay put
    cp = solve_spd((op.T @ inner @ op).tocsr(), op.T @ rhs, tikhonov=1e-12)
    return ts.with_control_points(cp)


# ------------------------------------------------------------------- folds
def element_turns_deg(ts: TSpline, samples: int = FOLD_SAMPLES) -> np.ndarray:
    """(n_e,) degrees: per Bezier element, the largest turn of the normal between neighbouring samples of
    its ``samples`` x ``samples`` grid (``splines.folds``: above ``FOLD_TURN_DEG`` the element folds)."""
    ext = ts.extraction
    gs = element_grid(ext.s_bounds[:, 0], ext.s_bounds[:, 1], samples)
    gt = element_grid(ext.t_bounds[:, 0], ext.t_bounds[:, 1], samples)
    n_e = ext.n_elements
    ss = np.broadcast_to(gs[:, :, None], (n_e, samples, samples))
    tt = np.broadcast_to(gt[:, None, :], (n_e, samples, samples))
    s, t = _wrap_clamp(ts, ss.ravel(), tt.ravel())
    sample = ts.evaluate(s, t, order=1)
    shape = (n_e, samples, samples, 3)
    return largest_turn_deg(sample.du.reshape(shape), sample.dv.reshape(shape))


# ------------------------------------------------------------------- statistics
def fit_stats(ts: TSpline, distance: np.ndarray, weights: np.ndarray, within_mm: float) -> FitStats:
    w = weights / weights.sum()
    return FitStats(
        control_points=ts.n_control,
        elements=ts.extraction.n_elements,
        share_within=float(w[distance <= within_mm].sum()),
        max_mm=float(distance.max()),
        rms_mm=float(np.sqrt(np.sum(w * distance**2))),
    )


def element_sizes_mm(ts: TSpline) -> np.ndarray:
    """(n_e, 2) physical size of each Bezier element along s and along t: the
    chord lengths of its two mid-lines (mm), so the stopping size means the
    same at the apex, where parameter lines crowd, as on the shaft."""
    ext = ts.extraction
    sm, tm = ext.s_bounds.mean(axis=1), ext.t_bounds.mean(axis=1)
    eps_s = 1e-9 * np.diff(ext.s_bounds, axis=1)[:, 0]
    eps_t = 1e-9 * np.diff(ext.t_bounds, axis=1)[:, 0]
    n = ext.n_elements
    ends = ts.evaluate(np.concatenate([ext.s_bounds[:, 0] + eps_s, ext.s_bounds[:, 1] - eps_s, sm, sm]),
                       np.concatenate([tm, tm, ext.t_bounds[:, 0] + eps_t, ext.t_bounds[:, 1] - eps_t])).points
    a, b, c, d = ends[:n], ends[n : 2 * n], ends[2 * n : 3 * n], ends[3 * n :]
    return np.stack([np.linalg.norm(b - a, axis=1), np.linalg.norm(d - c, axis=1)], axis=1)


def _marked_elements(ts: TSpline, elem, distance, weights, tol: FitTolerances, frozen=None,
                     stalled: np.ndarray | None = None, share_held: bool = False,
                     noise_level: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Elements to refine: Doerfler marking of the weight beyond the tolerance.

    elem : (n,) element of each point. Elements are ranked by the weight
    (area) of their points beyond the tolerance distance; the smallest set
    holding ``mark_fraction`` of that weight (near the target, only
    ``mark_deficit_factor`` times the weight the share target still misses)
    is marked, plus every element with a point beyond the maximum deviation
    (only those once the share and the RMS targets hold). An element may be halved
    along s (t) only while its physical size along s (t) is at least twice
    ``min_element_mm``; those ``frozen`` (a function of element bounds ->
    bool) are left alone, and ``stalled`` points ((n,) bool, within the
    data's noise, see ``FitTolerances.noise_factor``) count for nothing;
    ``share_held`` (the share holds up to the data's noise): only the points
    beyond the maximum deviation ask for more.
    noise_level : a rough mesh's noise level (mm; 0: not rough). Its fit stops once the RMS residual is
    at that level, so the elements are ranked instead by their squared residual above it (sum of
    w (d^2 - level^2) over their points beyond it) and the fewest holding ``mark_fraction`` of that, or
    only ``noise_mark_factor`` times the squared residual still above the level over the whole
    surface (sum of w d^2 - level^2 sum of w), are marked: the last round does not overshoot into the
    noise; points beyond the maximum deviation ask for nothing more (the noise stop reports them).
    Returns (marked element indices, (n_e, 2) bool: which directions may be halved).
    """
    ext = ts.extraction
    n_e = ext.n_elements
    live = np.ones(len(distance), dtype=bool) if stalled is None else ~stalled
    bad = (distance > tol.share_within[1]) & live
    wbad = np.bincount(elem, weights * bad, minlength=n_e)
    worst = np.zeros(n_e)
    np.maximum.at(worst, elem, np.where(live, distance, 0.0))
    halvable = element_sizes_mm(ts) >= 2 * tol.min_element_mm
    eligible = halvable.any(axis=1)
    if frozen is not None:
        eligible &= ~frozen(ext.s_bounds, ext.t_bounds)
    if noise_level > 0:
        return _marked_above_noise(elem, distance, weights, tol, noise_level, np.asarray(eligible)), halvable
    wbad = np.where(eligible, wbad, 0.0)
    order = np.argsort(-wbad, kind="stable")
    cum = np.cumsum(wbad[order])
    marked = np.zeros(n_e, dtype=bool)
    deficit = tol.share_within[0] * weights.sum() - weights[distance <= tol.share_within[1]].sum()
    rms_met = np.sqrt(np.sum(weights * distance**2) / weights.sum()) <= tol.rms_mm
    # once the share and the RMS hold, only the points beyond the maximum ask for more
    if cum[-1] > 0 and (deficit > 0 or not rms_met) and not share_held:
        fraction = (tol.mark_fraction if deficit <= 0
                    else min(tol.mark_fraction, tol.mark_deficit_factor * deficit / cum[-1]))
        k = int(np.searchsorted(cum, fraction * cum[-1])) + 1
        marked[order[:k]] = True
    marked |= worst > tol.max_deviation_mm
    return np.flatnonzero(marked & eligible & ((wbad > 0) | (worst > tol.max_deviation_mm))), halvable


def _marked_above_noise(elem, distance, weights, tol: FitTolerances, noise_level: float,
                        eligible: np.ndarray) -> np.ndarray:
    """Rough data: the fewest eligible elements holding the squared residual above the noise level that the
    fit still has to lose (``_marked_elements``)."""
    excess = weights * np.maximum(distance**2 - noise_level**2, 0.0)
    energy = np.where(eligible, np.bincount(elem, excess, minlength=len(eligible)), 0.0)
    deficit = float(np.sum(weights * distance**2) - noise_level**2 * weights.sum())
    order = np.argsort(-energy, kind="stable")
    cum = np.cumsum(energy[order])
    if cum[-1] <= 0 or deficit <= 0:
        return np.zeros(0, dtype=np.int64)
    k = int(np.searchsorted(cum, min(tol.mark_fraction * cum[-1], tol.noise_mark_factor * deficit))) + 1
    return np.sort(order[:k][energy[order[:k]] > 0])


def _marked_adjacency(ext: BezierExtraction, marked: np.ndarray) -> sp.csr_matrix:
    """(m, m) symmetric csr 0/1: which of the marked elements share an edge
    (their grid cells lie side by side, across the periodic seam too)."""
    ce = ext.cell_element
    ce = np.vstack([ce, ce[:1]]) if ext.mesh.periodic else ce
    pairs = np.concatenate([np.stack([ce[:-1].ravel(), ce[1:].ravel()], axis=1),
                            np.stack([ce[:, :-1].ravel(), ce[:, 1:].ravel()], axis=1)])
    slot = np.full(ext.n_elements + 1, -1)  # index -1 (end-strip cells) stays unmarked
    slot[marked] = np.arange(len(marked))
    q = slot[pairs]
    q = q[(q >= 0).all(axis=1) & (q[:, 0] != q[:, 1])]
    m = len(marked)
    a = sp.csr_matrix((np.ones(len(q)), (q[:, 0], q[:, 1])), shape=(m, m))
    return ((a + a.T) > 0).astype(np.float64)


def _split_axes(marked: np.ndarray, elem, u, v, residual, weights, halvable, anisotropy: float,
                adjacency: sp.csr_matrix) -> np.ndarray:
    """(len(marked), 2) bool: halve each marked element in s, in t, or both.

    residual : (n,) signed distance of each point (mm); u, v : its local
    coordinates in its element. The residual a refinement along s can absorb
    varies with u: its weighted between-bin variance over four bins of u
    (likewise v). adjacency : (m, m) which marked elements share an edge
    (``_marked_adjacency``). The figures are summed over each connected
    cluster of marked elements, so that a cluster is halved one way: its new
    lines then continue into each other, where neighbours halved across each
    other would leave crossing T-junction extensions for the
    analysis-suitability closure to resolve with extra vertices. A cluster is
    halved only along s when its u figure exceeds ``anisotropy`` times its v
    figure (only along t in the mirror case), else both ways; directions
    below the size limit (``halvable``) are dropped.
    """
    axes = np.ones((len(marked), 2), dtype=bool)
    if np.isfinite(anisotropy) and len(marked):
        slot = np.full(len(halvable), -1)
        slot[marked] = np.arange(len(marked))
        k = slot[elem]
        sel = k >= 0
        k, w, r = k[sel], weights[sel], residual[sel]
        n = len(marked)
        wsum = np.bincount(k, w, minlength=n)
        mean2 = np.bincount(k, w * r, minlength=n) ** 2 / np.maximum(wsum, 1e-300)
        n_clusters, cluster = connected_components(adjacency, directed=False)
        spread = []
        for x in (u[sel], v[sel]):
            b = k * 4 + np.minimum((x * 4).astype(np.int64), 3)
            wb = np.bincount(b, w, minlength=4 * n)
            rb = np.bincount(b, w * r, minlength=4 * n)
            between = np.maximum((rb**2 / np.maximum(wb, 1e-300)).reshape(n, 4).sum(axis=1) - mean2, 0.0)
            spread.append(np.bincount(cluster, between, minlength=n_clusters)[cluster])
        axes[:, 1] = ~(spread[0] > anisotropy * spread[1])
        axes[:, 0] = ~(spread[1] > anisotropy * spread[0])
    axes &= halvable[marked]
    # an element that may be halved one way only is halved that way
    return axes | (~axes.any(axis=1, keepdims=True) & halvable[marked])


def _share_up_to_noise(distance: np.ndarray, weights: np.ndarray, stalled: np.ndarray, tol: FitTolerances) -> bool:
    """The share target holds when points within the data's noise count as fitted (the share target on
    within | stalled). Only when the noisy points beyond the tolerance outweigh the share the target leaves
    over (1 - share): else the strict target is reachable without following the noise, and the fit goes on.
    (The RMS bar is not asked: on a staircase the noise alone sets it.)"""
    beyond = distance > tol.share_within[1]
    if _share(weights, stalled & beyond) <= 1.0 - tol.share_within[0]:
        return False
    return _share(weights, ~beyond | stalled) >= tol.share_within[0]


def _meets_up_to_noise(distance: np.ndarray, weights: np.ndarray, stalled: np.ndarray, tol: FitTolerances) -> bool:
    """The tolerances hold up to the data's noise: the share (``_share_up_to_noise``), and no point beyond
    the noise and beyond the maximum deviation."""
    return (_share_up_to_noise(distance, weights, stalled, tol)
            and not np.any((distance > tol.max_deviation_mm) & ~stalled))


def _noise_note(distance: np.ndarray, weights: np.ndarray, stalled: np.ndarray, tol: FitTolerances) -> str:
    """How much of the surface the noise excuses, for the fit's stop reason."""
    return (f"{_share(weights, stalled & (distance > tol.share_within[1])):.2%} of the surface lies beyond "
            f"{tol.share_within[1]} mm but within {tol.noise_factor} x the local noise")


def _noise_stop(stats: FitStats, dist: np.ndarray, noise_level: float, tol: FitTolerances) -> str:
    """The stop reason of a rough mesh's fit once its RMS residual is at the data's noise level."""
    beyond = int(np.sum(dist > tol.max_deviation_mm))
    held = [f"{stats.share_within:.1%} within {tol.share_within[1]} mm"
            + ("" if stats.share_within >= tol.share_within[0] else f" (target {tol.share_within[0]:.0%})")]
    if beyond:
        held.append(f"{beyond} point{'s' if beyond != 1 else ''} beyond {tol.max_deviation_mm} mm (up to "
                    f"{dist.max():.2f} mm)")
    return (f"stopped at the data's noise: the RMS residual ({stats.rms_mm:.3f} mm) is at the data's noise level "
            f"({noise_level:.3f} mm), and a closer fit would follow the noise, not the bone; "
            + "; ".join(held) + " left as the noise's")


def _share(weights: np.ndarray, mask: np.ndarray) -> float:
    return float(weights[mask].sum() / weights.sum())


def _refine_globally(ts: TSpline, elements: np.ndarray, axes: np.ndarray) -> TSpline:
    """Insert complete knot lines through the middle of the given elements (tensor product kept):
    an s-line where ``axes[:, 0]``, a t-line where ``axes[:, 1]``."""
    ext = ts.extraction
    mesh = ts.mesh
    (s0, s1), (t0, t1) = mesh.s_range, mesh.t_range
    s_mid = np.unique(np.round(ext.s_bounds[elements[axes[:, 0]]].mean(axis=1), 12))
    t_mid = np.unique(np.round(ext.t_bounds[elements[axes[:, 1]]].mean(axis=1), 12))
    segs = [KnotSegment("s", float(v), t0, t1) for v in s_mid]
    if mesh.s_period is not None:
        segs += [KnotSegment("t", float(v), s0, s0 + mesh.s_period) for v in t_mid]
    else:
        segs += [KnotSegment("t", float(v), s0, s1) for v in t_mid]
    return insert_segments(ts, segs).tspline


def _signed_distance(ts: TSpline, points: np.ndarray, s, t, distance: np.ndarray) -> np.ndarray:
    """(n,) distance of each point from the surface (mm), positive on the side the normal ds x dt points to."""
    sample = ts.evaluate(s, t, order=1)
    side = np.einsum("ij,ij->i", points - sample.points, np.cross(sample.du, sample.dv))
    return np.where(side < 0, -distance, distance)


def fit_adaptive(
    ts: TSpline,
    points: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    s: np.ndarray | None = None,
    t: np.ndarray | None = None,
    tolerances: FitTolerances,
    fairness: float = 1e-4,
    mode: Literal["local", "global"] = "local",
    corrections: int = 2,
    constraints: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
    frozen=None,
    noise: np.ndarray | None = None,
    noise_level: float = 0.0,
    progress: Callable[[int, FitStats], None] | None = None,
    data_hook: Callable[[TSpline, np.ndarray, np.ndarray], tuple[np.ndarray, tuple | None]] | None = None,
) -> FitResult:
    """Fit ``ts`` to points, refining until the tolerances hold or the budget is spent.

    ts : the starting surface (its control points give the first parameters
        when s, t are not given). points : (n, 3) mm; weights : (n,) (area each
        point stands for; None: equal). mode : "local" (T-spline refinement of
        failing elements) or "global" (whole knot lines: tensor product).
    corrections : parameter corrections (projection + re-solve) per round.
    constraints : optional (points (m, 3), s (m,), t (m,), weights (m,)):
        extra data at fixed parameters (not projected), e.g. a boundary curve.
    frozen : optional function (s_bounds (n_e, 2), t_bounds (n_e, 2)) -> (n_e,)
        bool of elements never to refine.
    noise : optional (n,) mm, the data's local noise level (``local_noise_mm``);
        points within ``tolerances.noise_factor`` times it never ask for refinement.
    noise_level : the data's noise level (mm, ``noise_level_mm``) when the data are rough, else 0. Once
        the share and the RMS targets hold with the RMS residual at or below it (discrepancy principle: a
        closer fit follows the noise), the points beyond the maximum deviation are taken for noise and the
        fit stops there, saying so.
    progress : optional function called with (round, its FitStats) after each round (the caller's
        progress bar; at most ``tolerances.max_rounds + 1`` rounds).
    data_hook : optional function (current surface, s, t) -> (left out (n,) bool, extra data (points (m, 3), s,
        t, weights) or None), called before each solve: points left out of it (they still count in the
        statistics) and data added to it, e.g. where the points' parameters cross or leave a part of the
        domain bare, which would fold the surface (issue 45).
    """
    tol = tolerances
    if mode not in ("local", "global"):
        raise ValueError(f"mode: expected 'local' or 'global', got {mode!r}")
    points = np.asarray(points, dtype=np.float64)
    w = np.ones(len(points)) if weights is None else np.asarray(weights, dtype=np.float64)
    if s is None or t is None:
        s, t, _ = initial_parameters(ts, points)
    history: list[FitStats] = []
    stopped = ""
    noise_mm = None if noise is None else tol.noise_factor * np.asarray(noise, dtype=np.float64)
    for round_ in range(tol.max_rounds + 1):
        # refinement keeps the surface, so after the first round one correction suffices
        for _ in range(corrections if round_ == 0 else 1):
            ws, extra = w, [constraints]
            if data_hook is not None:
                left_out, added = data_hook(ts, s, t)
                ws, extra = np.where(left_out, 0.0, w), [constraints, added]
            more = [e for e in extra if e is not None]  # each (points, s, t, weights)
            ts = solve_control_points(ts, np.concatenate([s, *(e[1] for e in more)]),
                                      np.concatenate([t, *(e[2] for e in more)]),
                                      np.vstack([points, *(e[0] for e in more)]),
                                      np.concatenate([ws, *(e[3] for e in more)]), fairness=fairness)
            s, t, dist = project_points(ts, points, s, t, iterations=3 if round_ == 0 else 2)
        stats = fit_stats(ts, dist, w, tol.share_within[1])
        history.append(stats)
        log.info("T-spline fit (%s) round %d: %s", mode, round_, stats.to_dict())
        if progress is not None:
            progress(round_, stats)
        # with a data hook that repairs folds, a surface that folds is not done: its folded elements are
        # refined (the hook puts their points right at each solve) until none is left or a limit stops the fit
        folded = (np.flatnonzero(element_turns_deg(ts) > FOLD_TURN_DEG) if data_hook is not None
                  else np.zeros(0, dtype=np.int64))
        if stats.meets(tol) and folded.size == 0:
            return FitResult(ts, s, t, dist, stats, history, True, "tolerances met", _folds(ts))
        if stats.meets(tol) and round_ < tol.max_rounds:
            log.info("T-spline fit (%s) round %d: the tolerances hold, but %d elements fold: refining them",
                     mode, round_, folded.size)
            new = refine_elements(ts, folded).tspline if mode == "local" else _refine_globally(
                ts, folded, np.ones((folded.size, 2), dtype=bool))
            if new.n_control <= tol.max_control_points:
                ts = new
                continue
        if stats.meets(tol):
            return FitResult(ts, s, t, dist, stats, history, True,
                             f"tolerances met; {folded.size} elements still fold (round or control-point limit)",
                             _folds(ts))
        if noise_level > 0 and stats.rms_mm <= noise_level:
            stopped = _noise_stop(stats, dist, noise_level, tol)
            break
        stalled = None if noise_mm is None else dist <= noise_mm
        if stalled is not None and _meets_up_to_noise(dist, w, stalled, tol):
            stopped = (f"tolerances met up to the data's noise: {_noise_note(dist, w, stalled, tol)}; "
                       f"no point beyond {tol.max_deviation_mm} mm asks for more")
            break
        if round_ == tol.max_rounds:
            stopped = f"round limit ({tol.max_rounds}) reached"
            break
        elem, u, v = ts.extraction.locate(s, t)
        share_held = stalled is not None and _share_up_to_noise(dist, w, stalled, tol)
        marked, halvable = _marked_elements(ts, elem, dist, w, tol, frozen, stalled, share_held, noise_level)
        if marked.size == 0 and stalled is not None and share_held:
            stopped = (f"tolerances met up to the data's noise: {_noise_note(dist, w, stalled, tol)}; the "
                       f"{int(np.sum(dist > tol.max_deviation_mm))} points beyond {tol.max_deviation_mm} mm (up to "
                       f"{dist.max():.2f} mm) lie in elements that may not be split further (size limit "
                       f"{2 * tol.min_element_mm} mm), where no refinement reaches")
            break
        if marked.size == 0:
            stopped = f"no element larger than {2 * tol.min_element_mm} mm misses the tolerance"
            if stalled is not None:
                stopped += f" beyond the data's noise ({_noise_note(dist, w, stalled, tol)})"
            break
        axes = _split_axes(marked, elem, u, v, _signed_distance(ts, points, s, t, dist), w, halvable,
                           tol.split_anisotropy, _marked_adjacency(ts.extraction, marked))
        new = refine_elements(ts, marked, axes).tspline if mode == "local" else _refine_globally(ts, marked, axes)
        if new.n_control > tol.max_control_points:
            stopped = f"control-point budget ({tol.max_control_points}) reached: the next round needs {new.n_control}"
            break
        ts = new
    return FitResult(ts, s, t, dist, stats, history, False, stopped, _folds(ts))


def _folds(ts: TSpline) -> int:
    """The number of Bezier elements of the final surface that fold (``element_turns_deg``)."""
    return int(np.sum(element_turns_deg(ts) > FOLD_TURN_DEG))
