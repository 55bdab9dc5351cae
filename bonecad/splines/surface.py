"""Tensor-product B-spline surfaces in numpy, and the interpolation used to skin and loft them.

Conventions match :mod:`bonecad.splines.curve`: a periodic direction has
uniform knots ``linspace(0, 1, n + 1)`` (one period, single knots: C2 with no
seam, unlike OpenCascade's periodic interpolation, which leaves a double knot
at the start); a clamped direction carries its full knot sequence on [0, 1].

References: L. Piegl, W. Tiller, *The NURBS Book*, 2nd ed. (1997), 9.2.1
(global interpolation, knots by averaging, eq. 9.8) and 10.3 (skinning).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bonecad.splines.basis import design_matrix
from bonecad.splines.curve import BSplineCurve
from bonecad.splines.knots import periodic_knots
from bonecad.splines.lsq import solve_dense
from bonecad.errors import FitError

#: Largest condition number accepted for an interpolation system.
_MAX_CONDITION = 1e8


@dataclass(frozen=True)
class BSplineSurface:
    """A polynomial B-spline surface S(u, v) on [0, 1]^2 (mm), u the first pole index.

    poles : (nu, nv, 3) float64
    knots_u, knots_v : full clamped knot sequence (nu + degree + 1 entries), or for a
        periodic direction the n + 1 uniform knots of one period
    reversed : the face uses the surface with its normal flipped, i.e. its outward
        normal is -(S_u x S_v); False for every surface bonecad builds itself
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

    def __post_init__(self) -> None:
        poles = np.array(self.poles, dtype=np.float64)  # defensive copy
        if poles.ndim != 3 or poles.shape[2] != 3:
            raise ValueError(f"poles must be (nu, nv, 3), got {poles.shape}")
        object.__setattr__(self, "poles", poles)
        for name, n, degree, periodic in (
            ("knots_u", poles.shape[0], self.degree_u, self.periodic_u),
            ("knots_v", poles.shape[1], self.degree_v, self.periodic_v),
        ):
            knots = np.array(getattr(self, name), dtype=np.float64)
            expected = n + 1 if periodic else n + degree + 1
            if len(knots) != expected:
                raise ValueError(f"{name} has {len(knots)} entries, expected {expected} "
                                 f"for {n} poles of degree {degree}")
            if periodic and not np.allclose(knots, periodic_knots(n), atol=1e-12):
                raise ValueError(f"{name}: a periodic direction needs uniform knots on [0, 1]")
            object.__setattr__(self, name, knots)

    @property
    def shape(self) -> tuple[int, int]:
        return self.poles.shape[0], self.poles.shape[1]

    @property
    def control_points(self) -> int:
        return int(self.poles.shape[0] * self.poles.shape[1])

    def _basis(self, t: np.ndarray, direction: str) -> np.ndarray:
        if direction == "u":
            return design_matrix(t, self.knots_u, self.degree_u, self.periodic_u, self.poles.shape[0]).toarray()
        return design_matrix(t, self.knots_v, self.degree_v, self.periodic_v, self.poles.shape[1]).toarray()

    def grid(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(len(u), len(v), 3) points on the parameter grid u x v."""
        bu = self._basis(np.asarray(u, dtype=np.float64), "u")
        bv = self._basis(np.asarray(v, dtype=np.float64), "v")
        return np.einsum("ia,abk,jb->ijk", bu, self.poles, bv)

    def __call__(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(m, 3) points at the parameter pairs (u[i], v[i])."""
        u, v = np.broadcast_arrays(np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64))
        bu = self._basis(u.ravel(), "u")
        bv = self._basis(v.ravel(), "v")
        return np.einsum("ia,abk,ib->ik", bu, self.poles, bv)

    def iso_u_curve(self, v: float) -> BSplineCurve:
        """The curve u -> S(u, v) (exact: its poles are the v-blend of the pole rows)."""
        bv = self._basis(np.array([float(v)]), "v")[0]
        return BSplineCurve(np.einsum("abk,b->ak", self.poles, bv), self.knots_u, self.degree_u, self.periodic_u)

    def transformed(self, matrix: np.ndarray, offset: np.ndarray) -> BSplineSurface:
        """The same surface under x -> x @ matrix + offset (exact). A mirror (det < 0) flips the
        v direction so that S_u x S_v keeps pointing the same way relative to the solid (outward)."""
        poles = self.poles @ np.asarray(matrix, dtype=np.float64) + np.asarray(offset, dtype=np.float64)
        moved = BSplineSurface(poles, self.knots_u, self.knots_v, self.degree_u, self.degree_v,
                               self.periodic_u, self.periodic_v, self.region, self.reversed)
        return moved.reversed_v() if np.linalg.det(matrix) < 0 else moved

    def reversed_v(self) -> BSplineSurface:
        """The same point set with v -> 1 - v (normal flipped). Clamped v only."""
        if self.periodic_v:
            raise ValueError("reversed_v: only a clamped v direction can be reversed")
        return BSplineSurface(self.poles[:, ::-1], self.knots_u, (1.0 - self.knots_v)[::-1], self.degree_u,
                              self.degree_v, self.periodic_u, self.periodic_v, self.region, self.reversed)

    def to_dict(self) -> dict:
        return {
            "region": self.region,
            "degrees": [self.degree_u, self.degree_v],
            "periodic": [self.periodic_u, self.periodic_v],
            "poles_shape": list(self.shape),
            "knots_u": self.knots_u.tolist(),
            "knots_v": self.knots_v.tolist(),
        }


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


def interpolate_clamped(values: np.ndarray, params: np.ndarray, degree: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """(poles, knots) of the clamped B-spline through values (n, ...) at increasing params (n,) on [0, 1]."""
    values = np.asarray(values, dtype=np.float64)
    params = np.asarray(params, dtype=np.float64)
    n = len(values)
    if params.shape != (n,) or np.any(np.diff(params) <= 0) or params[0] != 0.0 or params[-1] != 1.0:
        raise FitError("clamped interpolation parameters must increase from 0 to 1, one per value")
    knots = averaged_interpolation_knots(params, degree)
    matrix = design_matrix(params, knots, degree, False, n).toarray()
    flat = values.reshape(n, -1)
    poles = solve_dense(matrix, flat, max_condition=_MAX_CONDITION, what="clamped interpolation")
    return poles.reshape(values.shape), knots
