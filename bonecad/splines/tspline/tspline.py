"""The T-spline surface: a T-mesh, one control point and weight per anchor.

    S(s, t) = sum_A w_A P_A B_A(s, t) / sum_A w_A B_A(s, t),
    B_A(s, t) = N[s_A](s) N[t_A](t)

with the local knot vectors s_A, t_A from ray casting (Sederberg, Zheng,
Bakenov, Nasri 2003, "T-splines and T-NURCCs", sec. 3). Fast evaluation goes
through Bezier extraction (one bicubic rational patch per element);
``blending_values`` evaluates the definition directly and is the reference
the extraction is tested against.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from math import comb

import numpy as np
import scipy.sparse as sp

from bonecad.splines.basis import bernstein3
from bonecad.splines.tspline.basis import bspline5, knot_span
from bonecad.splines.surface import SurfaceSample
from bonecad.splines.tspline.extraction import BezierExtraction, extract
from bonecad.splines.tspline.tmesh import TMesh

#: Points evaluated per batch: their gathered Bezier patches (4 MB) stay in cache.
_BATCH = 8192


@dataclass(frozen=True, eq=False)
class TSpline:
    """A cubic (rational) T-spline surface.

    mesh : the T-mesh.
    control_points : (n, 3) float, mm, one per anchor in ``mesh.anchors`` order.
    weights : (n,) float > 0 (all 1: a polynomial T-spline).
    """

    mesh: TMesh
    control_points: np.ndarray
    weights: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.mesh.anchors)
        cp = np.array(self.control_points, dtype=np.float64)
        w = np.array(self.weights, dtype=np.float64)
        if cp.shape != (n, 3):
            raise ValueError(f"control_points: the T-mesh has {n} anchors, expected ({n}, 3), got {cp.shape}")
        if w.shape != (n,):
            raise ValueError(f"weights: expected ({n},), got {w.shape}")
        if not (np.all(np.isfinite(cp)) and np.all(np.isfinite(w)) and np.all(w > 0)):
            raise ValueError("control_points and weights must be finite, weights positive")
        object.__setattr__(self, "control_points", cp)
        object.__setattr__(self, "weights", w)

    @classmethod
    def from_grid(cls, s_knots, t_knots, control_points, weights=None, *, s_period: float | None = None) -> TSpline:
        """A tensor-product T-spline (a B-spline/NURBS surface written as a T-spline).

        s_knots, t_knots : distinct knot values (see ``TMesh.grid``).
        control_points : (m_s, m_t, 3) mm, indexed [s, t]; m_s = len(s_knots)
            when periodic, len(s_knots) + 2 when clamped; m_t = len(t_knots) + 2.
        weights : (m_s, m_t) or None (all 1).
        """
        mesh = TMesh.grid(s_knots, t_knots, s_period=s_period)
        cp = np.asarray(control_points, dtype=np.float64)
        s_n, t_n = mesh.shape
        m_s = s_n if mesh.periodic else s_n - 4
        m_t = t_n - 4
        if cp.shape != (m_s, m_t, 3):
            raise ValueError(f"control_points: expected ({m_s}, {m_t}, 3) for these knots, got {cp.shape}")
        w = np.ones((m_s, m_t)) if weights is None else np.asarray(weights, dtype=np.float64)
        if w.shape != (m_s, m_t):
            raise ValueError(f"weights: expected ({m_s}, {m_t}), got {w.shape}")
        # anchors are ordered by t-line, then s-line
        return cls(mesh, cp.transpose(1, 0, 2).reshape(-1, 3), w.T.ravel())

    # ------------------------------------------------------------ properties
    @property
    def n_control(self) -> int:
        """Number of control points."""
        return len(self.control_points)

    @cached_property
    def anchor_params(self) -> np.ndarray:
        """(n, 2) float: (s, t) knot values of each anchor."""
        a = self.mesh.anchors
        return np.stack([self.mesh.s_value(a[:, 0]), self.mesh.t_lines[a[:, 1]]], axis=1)

    @cached_property
    def extraction(self) -> BezierExtraction:
        """The Bezier extraction of the T-mesh, computed once per T-spline and handed on by
        ``with_control_points`` (a fit re-solves control points on one mesh many times)."""
        return extract(self.mesh)

    def with_control_points(self, control_points: np.ndarray, weights: np.ndarray | None = None) -> TSpline:
        """The T-spline on the same T-mesh with other control points (weights default to 1),
        sharing this one's Bezier extraction."""
        w = np.ones(len(control_points)) if weights is None else weights
        new = TSpline(self.mesh, control_points, w)
        if "extraction" in self.__dict__:
            new.__dict__["extraction"] = self.__dict__["extraction"]
        return new

    @cached_property
    def bezier_homogeneous(self) -> np.ndarray:
        """(n_e, 4, 4, 4) float: [w x, w y, w z, w] Bezier control points per element, [a, b, :]."""
        pw = np.hstack([self.control_points * self.weights[:, None], self.weights[:, None]])
        q = self.extraction.operator @ pw
        return q.reshape(-1, 4, 4, 4)

    @cached_property
    def polynomial(self) -> bool:
        """All weights 1: the surface is polynomial (as every fitted T-spline is)."""
        return bool(np.all(self.weights == 1.0))

    @cached_property
    def _evaluation_patches(self) -> np.ndarray:
        """Contiguous Bezier patches for ``evaluate``: (n_e, 4, 4, 3) points of a polynomial
        surface (its weight row is 1: no quotient rule), else the homogeneous (n_e, 4, 4, 4)."""
        return np.ascontiguousarray(self.bezier_homogeneous[..., :3]) if self.polynomial else self.bezier_homogeneous

    @property
    def bezier_points(self) -> tuple[np.ndarray, np.ndarray]:
        """Rational Bezier patches: ((n_e, 4, 4, 3) points in mm, (n_e, 4, 4) weights)."""
        q = self.bezier_homogeneous
        return q[..., :3] / q[..., 3:], q[..., 3].copy()

    # ------------------------------------------------------------ evaluation
    def evaluate(self, s, t, *, order: int = 0) -> SurfaceSample:
        """Surface points (and derivatives up to ``order`` <= 2) at (s, t).

        s, t : (n,) float parameters (the sample's u, v: ``du`` is the s-derivative). Uses the Bezier
        patches; vectorised.
        """
        if order not in (0, 1, 2):
            raise ValueError(f"order: expected 0, 1 or 2, got {order!r}")
        ext = self.extraction
        elem, u, v = ext.locate(s, t)
        n = len(elem)
        bu = bernstein3(u, order)
        bv = bernstein3(v, order)
        patches = self._evaluation_patches
        width = patches.shape[-1]
        hom = {(a, b): np.empty((n, width)) for a in range(order + 1) for b in range(order + 1 - a)}
        for lo in range(0, n, _BATCH):
            sl = slice(lo, min(lo + _BATCH, n))
            q = patches[elem[sl]]  # (m, 4, 4, 4): a cache-sized batch of gathered patches
            for a in range(order + 1):
                along_u = np.einsum("ma,mabk->mbk", bu[a][sl], q)
                for b in range(order + 1 - a):
                    hom[(a, b)][sl] = np.einsum("mb,mbk->mk", bv[b][sl], along_u)
        if order:
            hs = 1.0 / (ext.s_bounds[elem, 1] - ext.s_bounds[elem, 0])
            ht = 1.0 / (ext.t_bounds[elem, 1] - ext.t_bounds[elem, 0])
            for (a, b), h in hom.items():
                if a or b:
                    h *= (hs**a * ht**b)[:, None]  # d/ds = (1 / element width) d/du
        d = hom if self.polynomial else _rational_derivatives(hom, order)
        if order == 0:
            return SurfaceSample(d[(0, 0)])
        if order == 1:
            return SurfaceSample(d[(0, 0)], (d[(1, 0)], d[(0, 1)]))
        return SurfaceSample(d[(0, 0)], (d[(1, 0)], d[(0, 1)], d[(2, 0)], d[(1, 1)], d[(0, 2)]))

    def basis_matrix(self, s, t, *, ds: int = 0, dt: int = 0) -> sp.csr_matrix:
        """Rational basis functions R_A (or a partial derivative) at points.

        s, t : (n,) float. ds, dt : derivative orders, ds + dt <= 2.
        Returns csr (n, n_control): S^(ds,dt)(s_k, t_k) = (M @ control_points)[k].
        At most 16 non-zeros per row for an analysis-suitable T-mesh.
        """
        if ds < 0 or dt < 0 or ds + dt > 2:
            raise ValueError(f"ds, dt: expected non-negative orders with ds + dt <= 2, got {ds}, {dt}")
        ext = self.extraction
        elem, u, v = ext.locate(s, t)
        order = ds + dt
        counts = np.diff(ext.pair_ptr)[elem]
        rows = np.repeat(np.arange(len(elem)), counts)
        start = np.repeat(ext.pair_ptr[elem] - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
        pair = start + np.arange(len(rows))
        cols = ext.pair_anchor[pair]
        coef = ext.pair_coef[pair].reshape(-1, 4, 4)
        bu = bernstein3(u, order)
        bv = bernstein3(v, order)
        hs = 1.0 / (ext.s_bounds[elem, 1] - ext.s_bounds[elem, 0])
        ht = 1.0 / (ext.t_bounds[elem, 1] - ext.t_bounds[elem, 0])
        w = self.weights[cols]
        wb, big_w = {}, {}
        for a in range(ds + 1):
            for b in range(dt + 1):
                val = np.einsum("nkl,nk,nl->n", coef, bu[a][rows], bv[b][rows]) * (hs**a * ht**b)[rows]
                wb[(a, b)] = w * val
                big_w[(a, b)] = np.bincount(rows, wb[(a, b)], minlength=len(elem))
        r: dict[tuple[int, int], np.ndarray] = {}
        for a in range(ds + 1):
            for b in range(dt + 1):
                acc = wb[(a, b)].copy()
                for c in range(a + 1):
                    for d in range(b + 1):
                        if (c, d) != (a, b):
                            acc -= comb(a, c) * comb(b, d) * r[(c, d)] * big_w[(a - c, b - d)][rows]
                r[(a, b)] = acc / big_w[(0, 0)][rows]
        return sp.csr_matrix((r[(ds, dt)], (rows, cols)), shape=(len(elem), self.n_control))

    def blending_values(self, s, t) -> np.ndarray:
        """Blending functions B_A(s, t) evaluated from their definition (dense).

        s, t : (n,) float. Returns (n, n_control) float. O(n * n_control):
        the reference for the extraction-based evaluation, for small n.
        """
        mesh = self.mesh
        s = np.asarray(s, dtype=np.float64).ravel()
        t = np.asarray(t, dtype=np.float64).ravel()
        s_idx, t_idx = mesh.anchor_knots
        ks, kt = mesh.s_value(s_idx), mesh.t_lines[t_idx]
        t0, t1 = mesh.t_range
        t = np.minimum(np.clip(t, t0, t1), np.nextafter(t1, t0))
        n, m = len(s), len(ks)
        ks_r = np.tile(ks, (n, 1))
        kt_r = np.tile(kt, (n, 1))
        tt = np.repeat(t, m)
        if mesh.s_period is not None:
            ss = ks_r[:, 0] + np.mod(np.repeat(s, m) - ks_r[:, 0], mesh.s_period)
        else:
            s0, s1 = mesh.s_range
            ss = np.repeat(np.minimum(np.clip(s, s0, s1), np.nextafter(s1, s0)), m)
        ns = bspline5(ks_r, ss, knot_span(ks_r, ss))[0]
        nt = bspline5(kt_r, tt, knot_span(kt_r, tt))[0]
        return (ns * nt).reshape(n, m)

    def evaluate_direct(self, s, t) -> np.ndarray:
        """Surface points from the definition (dense blending values). (n, 3) mm."""
        b = self.blending_values(s, t) * self.weights
        return (b @ self.control_points) / b.sum(axis=1, keepdims=True)


def _rational_derivatives(hom: dict, order: int) -> dict:
    """Derivatives of x = X / W from those of homogeneous [X, W] (Leibniz rule)."""
    w = {k: v[:, 3:] for k, v in hom.items()}
    out: dict[tuple[int, int], np.ndarray] = {}
    for tot in range(order + 1):
        for a in range(tot, -1, -1):
            b = tot - a
            acc = hom[(a, b)][:, :3].copy()
            for c in range(a + 1):
                for d in range(b + 1):
                    if (c, d) != (a, b):
                        acc -= comb(a, c) * comb(b, d) * w[(a - c, b - d)] * out[(c, d)]
            out[(a, b)] = acc / w[(0, 0)]
    return out
