"""Point projection (point inversion) onto splines: foot points by Newton-type iteration.

- :func:`project_to_curve`: Newton on |C(u) - x|^2 (a fixed number of steps,
  parameters clamped or wrapped), from given parameters or from the nearest of
  dense samples (KD-tree);
- :func:`project_faces`: Gauss-Newton onto the rational surfaces of a
  :class:`~bonecad.splines.surface.SurfaceSet`, per-point stopping on the
  step length, clamped to each face's bounds or wrapped round a closed direction.

The T-spline fit's damped full Newton (``tspline.fit.project_points``) keeps its
own iteration: its step halving and stopping rule set the refinement's figures.

References: L. Piegl, W. Tiller, *The NURBS Book*, 2nd ed. (1997), 6.1 (point inversion).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

if TYPE_CHECKING:
    from bonecad.splines.surface import SurfaceSet


def project_to_curve(curve, points: np.ndarray, u: np.ndarray | None = None, *, iterations: int = 4,
                     samples: int = 2000) -> np.ndarray:
    """(m,) foot-point parameters of ``points`` (m, 3) on a :class:`~bonecad.splines.curve.BSplineCurve`.

    u : starting parameters (m,); None starts each point at the nearest of ``samples``
    curve points. Then ``iterations`` Newton steps u -= (C - x).C' / (C'.C' + (C - x).C''),
    clamped to [0, 1] (wrapped for a periodic curve).
    """
    if u is None:
        s = np.linspace(0.0, 1.0, samples, endpoint=not curve.periodic)
        _, nearest = cKDTree(curve(s)).query(points)
        u = s[nearest]
    u = np.array(u, dtype=np.float64)
    for _ in range(iterations):
        c0, c1, c2 = curve(u), curve(u, 1), curve(u, 2)
        diff = c0 - points
        num = np.einsum("ij,ij->i", diff, c1)
        den = np.einsum("ij,ij->i", c1, c1) + np.einsum("ij,ij->i", diff, c2)
        step = np.where(np.abs(den) > 1e-12, num / np.where(den == 0, 1.0, den), 0.0)
        u = u - step
        u = np.mod(u, 1.0) if curve.periodic else np.clip(u, 0.0, 1.0)
    return u


@dataclass(frozen=True)
class Projection:
    """Foot points of a projection onto one surface (all arrays have N rows).

    uv : (N, 2) parameters of the foot point
    foot : (N, 3) mm, the surface point S(u, v)
    normal : (N, 3) unit normal S_u x S_v (not yet oriented by the face)
    residual_mm : (N,) tangential part of (point - foot): zero at an exact foot point
    clamped : (N,) bool, the iteration hit the parameter bounds
    """

    uv: np.ndarray
    foot: np.ndarray
    normal: np.ndarray
    residual_mm: np.ndarray
    clamped: np.ndarray


def project_faces(
    surfaces: SurfaceSet,
    face: np.ndarray,
    points: np.ndarray,
    uv_start: np.ndarray,
    *,
    max_iterations: int = 30,
    tol_mm: float = 1e-7,
    chunk: int = 65536,
) -> Projection:
    """Foot points of ``points`` (N, 3) on the surfaces of faces ``face`` (N,) by Gauss-Newton from ``uv_start`` (N, 2).

    Each step solves the 2x2 normal equations J^T J duv = J^T (p - S) with
    J = [S_u S_v], then clamps to the face's ``bounds`` (or wraps round a closed
    direction). Started near the foot point it converges to it at a rate of
    about |distance| x curvature per step; points stop iterating once their
    step moves the surface point less than ``tol_mm``. ``residual_mm`` tells
    whether a point converged. A point clamped in two successive steps stops
    there (its foot point lies beyond the face; one clamp may be an overshoot).
    """
    points = np.asarray(points, dtype=np.float64)
    face = np.asarray(face, dtype=np.int64)
    uv = np.array(uv_start, dtype=np.float64, copy=True)
    lo_b = surfaces.bounds[face][:, [0, 2]]
    hi_b = surfaces.bounds[face][:, [1, 3]]
    closed = surfaces.closed[face]
    clamped = np.zeros(len(points), dtype=bool)
    for lo in range(0, len(points), chunk):
        active = np.arange(lo, min(lo + chunk, len(points)))
        was_clamped = np.zeros(len(active), dtype=bool)
        for _ in range(max_iterations):
            if len(active) == 0:
                break
            cur = uv[active]
            sample = surfaces.evaluate(face[active], cur[:, 0], cur[:, 1], order=1)
            s, su, sv = sample.points, sample.du, sample.dv
            r = points[active] - s
            a = np.einsum("ij,ij->i", su, su)
            b = np.einsum("ij,ij->i", su, sv)
            c = np.einsum("ij,ij->i", sv, sv)
            g1 = np.einsum("ij,ij->i", su, r)
            g2 = np.einsum("ij,ij->i", sv, r)
            det = a * c - b * b
            ok = det > 1e-300
            safe = np.where(ok, det, 1.0)
            du = np.where(ok, (c * g1 - b * g2) / safe, 0.0)
            dv = np.where(ok, (a * g2 - b * g1) / safe, 0.0)
            nxt = cur + np.column_stack([du, dv])
            lo_a, hi_a = lo_b[active], hi_b[active]
            wrap = closed[active]
            if wrap.any():
                nxt = np.where(wrap, lo_a + np.mod(nxt - lo_a, hi_a - lo_a), nxt)
            hit = np.any((nxt < lo_a) | (nxt > hi_a), axis=1)
            uv[active] = np.clip(nxt, lo_a, hi_a)
            clamped[active] = hit
            step = np.sqrt(du * du * a + 2 * du * dv * b + dv * dv * c)  # |du S_u + dv S_v|
            # a step past a bound is clamped and tried once more (an overshoot near the
            # edge); clamped twice running, the foot point lies beyond the face
            keep = (step > tol_mm) & ~(hit & was_clamped)
            active, was_clamped = active[keep], hit[keep]
    s = np.empty((len(points), 3))
    n = np.empty((len(points), 3))
    for lo in range(0, len(points), chunk):
        sl = slice(lo, lo + chunk)
        sample = surfaces.evaluate(face[sl], uv[sl, 0], uv[sl, 1], order=1)
        s[sl] = sample.points
        n[sl] = np.cross(sample.du, sample.dv)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = n / np.where(norm > 0, norm, 1.0)
    r = points - s
    tangential = r - np.einsum("ij,ij->i", r, n)[:, None] * n
    return Projection(uv, s, n, np.linalg.norm(tangential, axis=1), clamped)
