"""Vectorised evaluation of (rational) B-spline surfaces, one or many at once.

The deviation analysis refines distances on the exact surface of each CAD face
(DESIGN.md: "exact point-to-surface projection wherever the tessellation error
would matter"). Calling OpenCascade once per point costs microseconds each; here
the surface is copied once into numpy arrays (knots, homogeneous poles) and
evaluated for all points at once.

References: L. Piegl, W. Tiller, *The NURBS Book*, 2nd ed. (1997): A2.1 (span),
A2.2/A2.3 (basis functions and derivatives, :mod:`bonecad.splines.basis`), eq. 4.20
(rational derivatives). Projection onto these surfaces: :mod:`bonecad.splines.project`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bonecad.splines.basis import basis_functions, find_span


@dataclass(frozen=True)
class SplineSurface:
    """A clamped (non-periodic) rational B-spline surface as numpy arrays.

    degree_u, degree_v : int
    knots_u : (nu + degree_u + 1,) float, full knot sequence (multiplicities repeated)
    knots_v : (nv + degree_v + 1,) float
    poles_w : (nu, nv, 4) float, homogeneous poles (w*x, w*y, w*z, w), mm
    bounds : (4,) float, (u0, u1, v0, v1) parameter range of the face using it
    closed_u, closed_v : the face wraps round in u (v) over ``bounds``: projection
        steps past a bound continue from the other one instead of stopping
    """

    degree_u: int
    degree_v: int
    knots_u: np.ndarray
    knots_v: np.ndarray
    poles_w: np.ndarray
    bounds: np.ndarray
    closed_u: bool = False
    closed_v: bool = False

    def __post_init__(self) -> None:
        nu, nv = self.poles_w.shape[:2]
        if self.poles_w.ndim != 3 or self.poles_w.shape[2] != 4:
            raise ValueError(f"poles_w must be (nu, nv, 4), got {self.poles_w.shape}")
        if len(self.knots_u) != nu + self.degree_u + 1:
            raise ValueError(
                f"knots_u has {len(self.knots_u)} entries, expected nu + degree_u + 1 = "
                f"{nu + self.degree_u + 1}"
            )
        if len(self.knots_v) != nv + self.degree_v + 1:
            raise ValueError(
                f"knots_v has {len(self.knots_v)} entries, expected nv + degree_v + 1 = "
                f"{nv + self.degree_v + 1}"
            )


def evaluate(
    surface: SplineSurface, u: np.ndarray, v: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points and first partial derivatives at (u, v): three (N, 3) arrays S, S_u, S_v."""
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    return _Packed([surface]).evaluate(np.zeros(len(u), dtype=np.int64), u, v)


class _Packed:
    """Surfaces of one degree pair with their knots and poles concatenated (one direction per knot array)."""

    def __init__(self, surfaces: list[SplineSurface]):
        self.p = surfaces[0].degree_u
        self.q = surfaces[0].degree_v
        self.ku, self.ku_off, self.ku_key, self.nbu = self._direction([s.knots_u for s in surfaces], self.p)
        self.kv, self.kv_off, self.kv_key, self.nbv = self._direction([s.knots_v for s in surfaces], self.q)
        self.lo_u = np.array([s.knots_u[0] for s in surfaces])
        self.len_u = np.array([max(s.knots_u[-1] - s.knots_u[0], 1e-300) for s in surfaces])
        self.lo_v = np.array([s.knots_v[0] for s in surfaces])
        self.len_v = np.array([max(s.knots_v[-1] - s.knots_v[0], 1e-300) for s in surfaces])
        # the (p+1) x (q+1) poles of every span pair, contiguous: one row gather per point
        self.spans_v = self.nbv - self.q
        sizes = (self.nbu - self.p) * self.spans_v
        self.block_off = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        self.blocks = np.concatenate([self._blocks(s.poles_w, self.p, self.q) for s in surfaces])

    @staticmethod
    def _blocks(poles: np.ndarray, p: int, q: int) -> np.ndarray:
        nu, nv = poles.shape[:2]
        win = np.lib.stride_tricks.sliding_window_view(poles, (p + 1, q + 1), axis=(0, 1))  # (nu-p, nv-q, 4, p+1, q+1)
        return np.ascontiguousarray(np.moveaxis(win, 2, -1)).reshape((nu - p) * (nv - q), -1)

    @staticmethod
    def _direction(knot_list, degree):
        lengths = np.array([len(k) for k in knot_list])
        off = np.concatenate([[0], np.cumsum(lengths)[:-1]])
        # search keys: face f's knots mapped into [2f, 2f + 1], increasing over all faces
        keys = np.concatenate(
            [2.0 * f + (k - k[0]) / max(k[-1] - k[0], 1e-300) for f, k in enumerate(knot_list)]
        )
        return np.concatenate(knot_list), off, keys, lengths - degree - 1

    def _span(self, keys, key_off, nb, degree, lo, length, local, t):
        key = 2.0 * local + np.clip((t - lo[local]) / length[local], 0.0, 1.0)
        span = find_span(keys, key) - key_off[local]
        return np.clip(span, degree, nb[local] - 1) + key_off[local]

    def evaluate(self, local: np.ndarray, u: np.ndarray, v: np.ndarray):
        p, q = self.p, self.q
        su = self._span(self.ku_key, self.ku_off, self.nbu, p, self.lo_u, self.len_u, local, u)
        sv = self._span(self.kv_key, self.kv_off, self.nbv, q, self.lo_v, self.len_v, local, v)
        nu_, du = basis_functions(self.ku, p, u, su, 1)
        nv_, dv = basis_functions(self.kv, q, v, sv, 1)
        ids = self.block_off[local] + (su - self.ku_off[local] - p) * self.spans_v[local] + (
            sv - self.kv_off[local] - q
        )
        block = np.take(self.blocks, ids, axis=0).reshape(len(ids), p + 1, q + 1, 4)
        # one contraction per basis row: ~2x faster than stacking value and derivative rows
        along_u = np.einsum("na,nabc->nbc", nu_, block)  # (N, q+1, 4)
        along_u_du = np.einsum("na,nabc->nbc", du, block)
        sw = np.einsum("nb,nbc->nc", nv_, along_u)
        swv = np.einsum("nb,nbc->nc", dv, along_u)
        swu = np.einsum("nb,nbc->nc", nv_, along_u_du)
        w = sw[:, 3:4]
        point = sw[:, :3] / w
        return point, (swu[:, :3] - swu[:, 3:4] * point) / w, (swv[:, :3] - swv[:, 3:4] * point) / w


    def evaluate2(self, local: np.ndarray, u: np.ndarray, v: np.ndarray):
        """Points, first and second partials: S, S_u, S_v, S_uu, S_vv, S_uv ((N, 3) each; NURBS Book eq. 4.20)."""
        p, q = self.p, self.q
        su = self._span(self.ku_key, self.ku_off, self.nbu, p, self.lo_u, self.len_u, local, u)
        sv = self._span(self.kv_key, self.kv_off, self.nbv, q, self.lo_v, self.len_v, local, v)
        bu = basis_functions(self.ku, p, u, su, 2)  # (3, N, p+1)
        bv = basis_functions(self.kv, q, v, sv, 2)
        ids = self.block_off[local] + (su - self.ku_off[local] - p) * self.spans_v[local] + (
            sv - self.kv_off[local] - q
        )
        block = np.take(self.blocks, ids, axis=0).reshape(len(ids), p + 1, q + 1, 4)
        along_u = np.einsum("kna,nabc->knbc", bu, block)  # (3, N, q+1, 4): d^k/du^k
        h = {}
        for ku, kv in ((0, 0), (1, 0), (0, 1), (2, 0), (0, 2), (1, 1)):
            h[ku, kv] = np.einsum("nb,nbc->nc", bv[kv], along_u[ku])
        w = h[0, 0][:, 3:4]
        s = h[0, 0][:, :3] / w
        s_u = (h[1, 0][:, :3] - h[1, 0][:, 3:4] * s) / w
        s_v = (h[0, 1][:, :3] - h[0, 1][:, 3:4] * s) / w
        s_uu = (h[2, 0][:, :3] - 2 * h[1, 0][:, 3:4] * s_u - h[2, 0][:, 3:4] * s) / w
        s_vv = (h[0, 2][:, :3] - 2 * h[0, 1][:, 3:4] * s_v - h[0, 2][:, 3:4] * s) / w
        s_uv = (h[1, 1][:, :3] - h[1, 0][:, 3:4] * s_v - h[0, 1][:, 3:4] * s_u - h[1, 1][:, 3:4] * s) / w
        return s, s_u, s_v, s_uu, s_vv, s_uv


#: points per evaluation block (see ``SurfaceSet._dispatch``)
_EVAL_BLOCK = 16384


class SurfaceSet:
    """Many spline surfaces (one per face) evaluated and projected onto together.

    Points carry a face index; surfaces of equal degrees are packed into one set
    of arrays, so the work per call is a few numpy passes however many faces
    there are (a T-spline model has thousands of Bezier faces). ``None`` entries
    (faces without a spline surface) may not be evaluated.
    """

    def __init__(self, surfaces):
        self.surfaces = tuple(surfaces)
        count = len(self.surfaces)
        self.group = np.full(count, -1, dtype=np.int64)
        self.local = np.zeros(count, dtype=np.int64)
        self.bounds = np.zeros((count, 4))
        self.closed = np.zeros((count, 2), dtype=bool)
        keys: dict[tuple[int, int], list[int]] = {}
        for f, s in enumerate(self.surfaces):
            if s is None:
                continue
            keys.setdefault((s.degree_u, s.degree_v), []).append(f)
            self.bounds[f] = s.bounds
            self.closed[f] = (s.closed_u, s.closed_v)
        self._packs = []
        for g, members in enumerate(keys.values()):
            self.group[members] = g
            self.local[members] = np.arange(len(members))
            self._packs.append(_Packed([self.surfaces[f] for f in members]))

    def _dispatch(self, method: str, count: int, face, u, v):
        """Call ``_Packed.<method>`` on each degree group's points; ``count`` (N, 3) results.

        Points go in blocks of ``_EVAL_BLOCK``: the per-point pole blocks and basis
        temporaries then stay in cache (about 2x faster than one pass over 400k points).
        """
        face = np.asarray(face, dtype=np.int64)
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        group = self.group[face]
        if (group < 0).any():
            raise ValueError("cannot evaluate faces without a spline surface")
        out = [np.empty((len(face), 3)) for _ in range(count)]
        for g, pack in enumerate(self._packs):
            sel = np.arange(len(face)) if len(self._packs) == 1 else np.flatnonzero(group == g)
            for lo in range(0, len(sel), _EVAL_BLOCK):
                part = sel[lo : lo + _EVAL_BLOCK]
                for arr, val in zip(out, getattr(pack, method)(self.local[face[part]], u[part], v[part])):
                    arr[part] = val
        return tuple(out)

    def evaluate(self, face: np.ndarray, u: np.ndarray, v: np.ndarray):
        """Points and first partials (three (N, 3) arrays) at (u, v) on faces ``face`` (N,)."""
        return self._dispatch("evaluate", 3, face, u, v)

    def evaluate2(self, face: np.ndarray, u: np.ndarray, v: np.ndarray):
        """Points, first and second partials (S, S_u, S_v, S_uu, S_vv, S_uv; (N, 3) each) on faces ``face``."""
        return self._dispatch("evaluate2", 6, face, u, v)
