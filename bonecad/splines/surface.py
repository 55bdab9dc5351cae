"""Tensor-product (rational) B-spline surfaces in numpy, their batched evaluation, and the
interpolation used to skin and loft them.

One surface type, :class:`BSplineSurface`, for the surfaces bonecad builds (the
NURBS model's lofts: polynomial, periodic round the bone, domain [0, 1]) and
for every CAD face read back from OpenCascade (rational, clamped, with the
face's parameter bounds). :class:`SurfaceSet` evaluates many of them at once
(one per face, packed by degree pair); :meth:`BSplineSurface.evaluate` is the
same evaluator for one surface. Both return a :class:`SurfaceSample`.

Knot conventions match :mod:`bonecad.splines.curve` (:mod:`bonecad.splines.knots`):
a periodic direction has uniform knots ``linspace(0, 1, n + 1)`` (one period,
single knots: C2 with no seam, unlike OpenCascade's periodic interpolation,
which leaves a double knot at the start); a clamped direction carries its full
knot sequence. For evaluation a periodic direction is unrolled onto unclamped
knots with its first ``degree`` poles repeated (``unclamped_periodic``,
``wrapped_poles``).

References: L. Piegl, W. Tiller, *The NURBS Book*, 2nd ed. (1997): A2.1 (span),
A2.2/A2.3 (basis functions and derivatives, :mod:`bonecad.splines.basis`), eq. 4.20
(rational derivatives), 9.2.1 (global interpolation, knots by averaging, eq. 9.8)
and 10.3 (skinning). Projection onto these surfaces: :mod:`bonecad.splines.project`.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from bonecad.errors import FitError
from bonecad.splines.basis import basis_functions, design_matrix, find_span
from bonecad.splines.knots import periodic_knots, unclamped_periodic, wrapped_poles
from bonecad.splines.lsq import solve_dense

#: Largest condition number accepted for an interpolation system.
_MAX_CONDITION = 1e8


@dataclass(frozen=True)
class SurfaceSample:
    """Surface points and partial derivatives at n parameter points (u, v).

    points : (n, 3) mm
    derivatives : (n, 3) arrays, mm per unit parameter (squared): S_u, S_v when evaluated
        to order 1, then S_uu, S_uv, S_vv to order 2; read them as ``du`` .. ``dvv``
    """

    points: np.ndarray
    derivatives: tuple[np.ndarray, ...] = ()

    @property
    def order(self) -> int:
        """Highest derivative order held: 0, 1 or 2."""
        return {0: 0, 2: 1, 5: 2}[len(self.derivatives)]

    def _derivative(self, index: int, name: str) -> np.ndarray:
        if index >= len(self.derivatives):
            raise ValueError(f"{name} was not evaluated (sample of order {self.order})")
        return self.derivatives[index]

    @property
    def du(self) -> np.ndarray:
        return self._derivative(0, "du")

    @property
    def dv(self) -> np.ndarray:
        return self._derivative(1, "dv")

    @property
    def duu(self) -> np.ndarray:
        return self._derivative(2, "duu")

    @property
    def duv(self) -> np.ndarray:
        return self._derivative(3, "duv")

    @property
    def dvv(self) -> np.ndarray:
        return self._derivative(4, "dvv")


@dataclass(frozen=True)
class BSplineSurface:
    """A tensor-product B-spline surface S(u, v) in mm, u the first pole index; rational when weighted.

    poles : (nu, nv, 3) float64, mm
    knots_u, knots_v : full clamped knot sequence (n + degree + 1 entries), or for a
        periodic direction the n + 1 uniform knots of one period on [0, 1]
    weights : (nu, nv) float > 0, or None for a polynomial surface
    bounds : (4,) (u0, u1, v0, v1), the parameter range in use (of the face lying on
        the surface); a NaN entry (the default) is that end of the knot domain
        ([0, 1] in a periodic direction)
    closed_u, closed_v : the face wraps round in u (v) over ``bounds`` (projection steps
        past a bound continue from the other one); a periodic direction always wraps
    region : the face's name; reversed : the face uses the surface with its normal
        flipped, i.e. its outward normal is -(S_u x S_v); False for every surface
        bonecad builds itself
    """

    poles: np.ndarray
    knots_u: np.ndarray
    knots_v: np.ndarray
    degree_u: int = 3
    degree_v: int = 3
    periodic_u: bool = False
    periodic_v: bool = False
    region: str = ""
    reversed: bool = False
    weights: np.ndarray | None = None
    bounds: np.ndarray = field(default_factory=lambda: np.full(4, np.nan))
    closed_u: bool = False
    closed_v: bool = False

    def __post_init__(self) -> None:
        poles = np.array(self.poles, dtype=np.float64)  # defensive copy
        if poles.ndim != 3 or poles.shape[2] != 3:
            raise ValueError(f"poles must be (nu, nv, 3), got {poles.shape}")
        object.__setattr__(self, "poles", poles)
        if self.weights is not None:
            weights = np.array(self.weights, dtype=np.float64)
            if weights.shape != poles.shape[:2] or not np.all(weights > 0):
                raise ValueError(f"weights must be (nu, nv) = {poles.shape[:2]} and > 0, got {weights.shape}")
            object.__setattr__(self, "weights", weights)
        domain = []
        for name, n, degree, periodic in (
            ("knots_u", poles.shape[0], self.degree_u, self.periodic_u),
            ("knots_v", poles.shape[1], self.degree_v, self.periodic_v),
        ):
            knots = np.array(getattr(self, name), dtype=np.float64)
            expected = n + 1 if periodic else n + degree + 1
            if len(knots) != expected:
                raise ValueError(
                    f"{name} has {len(knots)} entries, expected {expected} for {n} poles of degree {degree}"
                )
            if periodic and not np.allclose(knots, periodic_knots(n), atol=1e-12):
                raise ValueError(f"{name}: a periodic direction needs uniform knots on [0, 1]")
            object.__setattr__(self, name, knots)
            domain += [knots[0], knots[-1]]
        bounds = np.array(self.bounds, dtype=np.float64)
        if bounds.shape != (4,):
            raise ValueError(f"bounds must be (u0, u1, v0, v1), got {bounds.shape}")
        bounds = np.where(np.isnan(bounds), domain, bounds)
        object.__setattr__(self, "bounds", bounds)

    @property
    def shape(self) -> tuple[int, int]:
        return self.poles.shape[0], self.poles.shape[1]

    @property
    def control_points(self) -> int:
        return int(self.poles.shape[0] * self.poles.shape[1])

    @property
    def rational(self) -> bool:
        return self.weights is not None

    @property
    def homogeneous_poles(self) -> np.ndarray:
        """(nu, nv, 4) poles (w x, w y, w z, w) in mm (w = 1 for a polynomial surface)."""
        if self.weights is None:
            return np.concatenate([self.poles, np.ones((*self.shape, 1))], axis=2)
        w = self.weights[..., None]
        return np.concatenate([self.poles * w, w], axis=2)

    def evaluate(self, u: np.ndarray, v: np.ndarray, *, order: int = 0) -> SurfaceSample:
        """Points (and partial derivatives up to ``order`` <= 2) at the parameter pairs (u[i], v[i]);
        u, v broadcast together and flatten to m points ((m, 3) arrays, mm)."""
        u, v = np.broadcast_arrays(np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64))
        u, v = u.ravel(), v.ravel()
        return SurfaceSet([self]).evaluate(np.zeros(len(u), dtype=np.int64), u, v, order=order)

    def transformed(self, matrix: np.ndarray, offset: np.ndarray) -> BSplineSurface:
        """The same surface under x -> x @ matrix + offset (exact, weights kept). A mirror (det < 0) flips the
        v direction so that S_u x S_v keeps pointing the same way relative to the solid (outward)."""
        poles = self.poles @ np.asarray(matrix, dtype=np.float64) + np.asarray(offset, dtype=np.float64)
        moved = replace(self, poles=poles)
        return moved.reversed_v() if np.linalg.det(matrix) < 0 else moved

    def reversed_v(self) -> BSplineSurface:
        """The same point set with v -> v0 + v1 - v over the knot domain [v0, v1] (normal flipped). Clamped v only."""
        if self.periodic_v:
            raise ValueError("reversed_v: only a clamped v direction can be reversed")
        knots = self.knots_v
        ends = knots[0] + knots[-1]
        bounds = self.bounds.copy()
        bounds[2:] = ends - bounds[:1:-1]
        weights = None if self.weights is None else self.weights[:, ::-1]
        return replace(self, poles=self.poles[:, ::-1], knots_v=(ends - knots)[::-1], weights=weights, bounds=bounds)

    def to_dict(self) -> dict:
        return {
            "region": self.region,
            "degrees": [self.degree_u, self.degree_v],
            "periodic": [self.periodic_u, self.periodic_v],
            "poles_shape": list(self.shape),
            "knots_u": self.knots_u.tolist(),
            "knots_v": self.knots_v.tolist(),
        }

    def packed(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(knots_u, knots_v, homogeneous poles) as the batched evaluator takes them: full knot sequences,
        a periodic direction unrolled onto unclamped knots with its first ``degree`` poles repeated."""
        knots_u, knots_v, poles = self.knots_u, self.knots_v, self.homogeneous_poles
        if self.periodic_u:
            knots_u = unclamped_periodic(self.shape[0], self.degree_u)
            poles = wrapped_poles(poles, self.degree_u, axis=0)
        if self.periodic_v:
            knots_v = unclamped_periodic(self.shape[1], self.degree_v)
            poles = wrapped_poles(poles, self.degree_v, axis=1)
        return knots_u, knots_v, poles


class _Packed:
    """Surfaces of one degree pair with their knots and poles concatenated (one direction per knot array)."""

    def __init__(self, surfaces: list[BSplineSurface]):
        self.p = surfaces[0].degree_u
        self.q = surfaces[0].degree_v
        knots_u, knots_v, poles = zip(*(s.packed() for s in surfaces))
        self.ku, self.ku_off, self.ku_key, self.nbu = self._direction(knots_u, self.p)
        self.kv, self.kv_off, self.kv_key, self.nbv = self._direction(knots_v, self.q)
        self.lo_u = np.array([k[0] for k in knots_u])
        self.len_u = np.array([max(k[-1] - k[0], 1e-300) for k in knots_u])
        self.lo_v = np.array([k[0] for k in knots_v])
        self.len_v = np.array([max(k[-1] - k[0], 1e-300) for k in knots_v])
        self.periodic_u = np.array([s.periodic_u for s in surfaces])
        self.periodic_v = np.array([s.periodic_v for s in surfaces])
        # the (p+1) x (q+1) poles of every span pair, contiguous: one row gather per point
        self.spans_v = self.nbv - self.q
        sizes = (self.nbu - self.p) * self.spans_v
        self.block_off = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        self.blocks = np.concatenate([self._blocks(pw, self.p, self.q) for pw in poles])

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

    def _locate(self, local: np.ndarray, u: np.ndarray, v: np.ndarray):
        """Periodic parameters wrapped into [0, 1); the knot spans (global indices) and pole blocks of the points."""
        p, q = self.p, self.q
        if self.periodic_u.any():
            u = np.where(self.periodic_u[local], np.mod(u, 1.0), u)
        if self.periodic_v.any():
            v = np.where(self.periodic_v[local], np.mod(v, 1.0), v)
        su = self._span(self.ku_key, self.ku_off, self.nbu, p, self.lo_u, self.len_u, local, u)
        sv = self._span(self.kv_key, self.kv_off, self.nbv, q, self.lo_v, self.len_v, local, v)
        ids = self.block_off[local] + (su - self.ku_off[local] - p) * self.spans_v[local] + (
            sv - self.kv_off[local] - q
        )
        block = np.take(self.blocks, ids, axis=0).reshape(len(ids), p + 1, q + 1, 4)
        return u, v, su, sv, block

    def evaluate(self, local: np.ndarray, u: np.ndarray, v: np.ndarray, order: int) -> tuple[np.ndarray, ...]:
        """S, and for ``order`` 1 also S_u, S_v ((N, 3) each; NURBS Book eq. 4.20)."""
        p, q = self.p, self.q
        u, v, su, sv, block = self._locate(local, u, v)
        bu = basis_functions(self.ku, p, u, su, order)
        bv = basis_functions(self.kv, q, v, sv, order)
        # one contraction per basis row: ~2x faster than stacking value and derivative rows
        along_u = np.einsum("na,nabc->nbc", bu[0], block)  # (N, q+1, 4)
        sw = np.einsum("nb,nbc->nc", bv[0], along_u)
        w = sw[:, 3:4]
        point = sw[:, :3] / w
        if order == 0:
            return (point,)
        along_u_du = np.einsum("na,nabc->nbc", bu[1], block)
        swv = np.einsum("nb,nbc->nc", bv[1], along_u)
        swu = np.einsum("nb,nbc->nc", bv[0], along_u_du)
        return point, (swu[:, :3] - swu[:, 3:4] * point) / w, (swv[:, :3] - swv[:, 3:4] * point) / w

    def evaluate2(self, local: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, ...]:
        """S, S_u, S_v, S_uu, S_uv, S_vv ((N, 3) each; NURBS Book eq. 4.20)."""
        p, q = self.p, self.q
        u, v, su, sv, block = self._locate(local, u, v)
        bu = basis_functions(self.ku, p, u, su, 2)  # (3, N, p+1)
        bv = basis_functions(self.kv, q, v, sv, 2)
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
        return s, s_u, s_v, s_uu, s_uv, s_vv


#: points per evaluation block (see ``SurfaceSet.evaluate``)
_EVAL_BLOCK = 16384


class SurfaceSet:
    """Many B-spline surfaces (one per face) evaluated and projected onto together.

    Points carry a face index; surfaces of equal degrees are packed into one set
    of arrays, so the work per call is a few numpy passes however many faces
    there are (a T-spline model has thousands of Bezier faces). ``None`` entries
    (faces without a spline surface, ``group`` -1) may not be evaluated.
    ``bounds`` (F, 4) and ``closed`` (F, 2) hold each face's parameter range and
    whether it wraps round in u, v (closed or periodic).
    """

    def __init__(self, surfaces: Sequence[BSplineSurface | None]):
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
            self.closed[f] = (s.closed_u or s.periodic_u, s.closed_v or s.periodic_v)
        self._packs = []
        for g, members in enumerate(keys.values()):
            self.group[members] = g
            self.local[members] = np.arange(len(members))
            self._packs.append(_Packed([s for s in (self.surfaces[f] for f in members) if s is not None]))

    def evaluate(self, face: np.ndarray, u: np.ndarray, v: np.ndarray, *, order: int = 0) -> SurfaceSample:
        """Points (and partial derivatives up to ``order`` <= 2) at (u, v) on faces ``face`` (N,); (N, 3), mm.

        Points go in blocks of ``_EVAL_BLOCK``: the per-point pole blocks and basis
        temporaries then stay in cache (about 2x faster than one pass over 400k points).
        """
        if order not in (0, 1, 2):
            raise ValueError(f"order: expected 0, 1 or 2, got {order!r}")
        face = np.asarray(face, dtype=np.int64)
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        group = self.group[face]
        if (group < 0).any():
            raise ValueError("cannot evaluate faces without a spline surface")
        out = [np.empty((len(face), 3)) for _ in range((1, 3, 6)[order])]
        for g, pack in enumerate(self._packs):
            sel = np.arange(len(face)) if len(self._packs) == 1 else np.flatnonzero(group == g)
            for lo in range(0, len(sel), _EVAL_BLOCK):
                part = sel[lo : lo + _EVAL_BLOCK]
                local = self.local[face[part]]
                values = (pack.evaluate2(local, u[part], v[part]) if order == 2
                          else pack.evaluate(local, u[part], v[part], order))
                for arr, val in zip(out, values):
                    arr[part] = val
        return SurfaceSample(out[0], tuple(out[1:]))


def interpolate_periodic(values: np.ndarray, params: np.ndarray | None = None) -> np.ndarray:
    """Poles of the periodic cubic with uniform knots (n poles) through n values.

    values : (n, ...) float, interpolated at ``params`` (n,) in [0, 1), increasing
        cyclically (the first may lie anywhere in the period); default the uniform
        parameters j / n, where the system is circulant (1/6, 4/6, 1/6) and always
        well posed. Returns poles shaped like ``values``.
    """
    values = np.asarray(values, dtype=np.float64)
    n = len(values)
    params = np.arange(n) / n if params is None else np.asarray(params, dtype=np.float64)
    if params.shape != (n,):
        raise ValueError(f"need one parameter per value: {params.shape} parameters, {n} values")
    steps = np.mod(np.diff(np.append(params, params[0])), 1.0)
    if np.any(params < 0) or np.any(params >= 1) or np.any(steps <= 0) or abs(steps.sum() - 1.0) > 1e-9:
        raise FitError("periodic interpolation parameters must lie in [0, 1) and go once round in order")
    matrix = design_matrix(params, periodic_knots(n), 3, True, n).toarray()
    flat = values.reshape(n, -1)
    return solve_dense(matrix, flat, max_condition=_MAX_CONDITION, what="periodic interpolation").reshape(values.shape)


def averaged_interpolation_knots(params: np.ndarray, degree: int = 3) -> np.ndarray:
    """Clamped knots for interpolation at ``params`` (NURBS Book eq. 9.8)."""
    n = len(params)
    if n < degree + 1:
        raise FitError(f"interpolation of degree {degree} needs at least {degree + 1} values, got {n}")
    inner = np.array([params[j:j + degree].mean() for j in range(1, n - degree)])
    return np.concatenate([np.zeros(degree + 1), inner, np.ones(degree + 1)])


def interpolate_clamped(values: np.ndarray, params: np.ndarray, degree: int = 3, *,
                        end_derivatives: tuple[np.ndarray, np.ndarray] | None = None
                        ) -> tuple[np.ndarray, np.ndarray]:
    """(poles, knots) of the clamped B-spline through values (n, ...) at increasing params (n,) on [0, 1].

    end_derivatives : (first derivative at 0, at 1), each shaped like one value; the
        curve then has n + 2 poles, the interior parameters as its interior knots
        (NURBS Book 9.2.2, cubic only), and those derivatives exactly.
    """
    values = np.asarray(values, dtype=np.float64)
    params = np.asarray(params, dtype=np.float64)
    n = len(values)
    if params.shape != (n,) or np.any(np.diff(params) <= 0) or params[0] != 0.0 or params[-1] != 1.0:
        raise FitError("clamped interpolation parameters must increase from 0 to 1, one per value")
    flat = values.reshape(n, -1)
    if end_derivatives is None:
        knots = averaged_interpolation_knots(params, degree)
        matrix = design_matrix(params, knots, degree, False, n).toarray()
        poles = solve_dense(matrix, flat, max_condition=_MAX_CONDITION, what="clamped interpolation")
        return poles.reshape(values.shape), knots
    if degree != 3 or n < 2:
        raise FitError(f"end-derivative interpolation is cubic through at least 2 values, got degree {degree}, {n}")
    knots = np.concatenate([np.zeros(4), params[1:-1], np.ones(4)])
    count = n + 2
    rows = design_matrix(params, knots, degree, False, count).toarray()
    start, end = np.zeros(count), np.zeros(count)
    # S'(0) = 3 (P1 - P0) / t4, S'(1) = 3 (P_last - P_last-1) / (1 - t_count-1)
    start[[0, 1]] = np.array([-1.0, 1.0]) * 3.0 / knots[4]
    end[[-2, -1]] = np.array([-1.0, 1.0]) * 3.0 / (1.0 - knots[count - 1])
    matrix = np.vstack([rows[:1], start, rows[1:-1], end, rows[-1:]])
    rhs = np.vstack([flat[:1], np.reshape(end_derivatives[0], (1, -1)), flat[1:-1],
                     np.reshape(end_derivatives[1], (1, -1)), flat[-1:]])
    poles = solve_dense(matrix, rhs, max_condition=_MAX_CONDITION, what="clamped interpolation with end derivatives")
    poles[[0, -1]] = flat[[0, -1]]  # a clamped end is its value: exactly, not to rounding
    return poles.reshape((count, *values.shape[1:])), knots


def end_derivative(poles: np.ndarray, knots: np.ndarray, degree: int, end: int) -> np.ndarray:
    """Poles of the first derivative at the start (``end`` 0) or the end (1) of a clamped direction,
    for poles (n, ...) along that direction: a curve in the other direction's basis (exact)."""
    n = len(poles)
    if end == 0:
        return degree * (poles[1] - poles[0]) / (knots[degree + 1] - knots[1])
    return degree * (poles[n - 1] - poles[n - 2]) / (knots[n + degree - 1] - knots[n - 1])
