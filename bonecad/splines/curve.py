"""Cubic B-spline curves in numpy: evaluation and least-squares fitting (projection: splines/project.py).

Open curves are clamped (end points interpolated); closed curves are periodic
with uniform knots (C2 everywhere, no seam: DESIGN.md warns that OpenCascade's
periodic interpolation leaves a double knot). Fitting follows Piegl & Tiller,
The NURBS Book, ch. 9.4 (least squares with parameter correction); knots of
open curves are placed by the averaging rule (eq. 9.68-9.69).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy import sparse
from scipy.interpolate import BSpline

from bonecad.errors import FitError
from bonecad.splines.basis import design_matrix
from bonecad.splines.knots import periodic_knots, unclamped_periodic, wrapped_poles
from bonecad.splines.lsq import normal_equations, solve_dense
from bonecad.splines.project import project_to_curve


@dataclass(frozen=True)
class BSplineCurve:
    """A degree-p B-spline curve in 3-D (mm), parameter domain [0, 1].

    control_points : (n, 3) float64
    knots : (n + p + 1,) for open curves (clamped); for periodic curves the
        n + 1 distinct knots of one period, uniform on [0, 1]
    """

    control_points: np.ndarray
    knots: np.ndarray
    degree: int = 3
    periodic: bool = False

    @cached_property
    def _spline(self) -> BSpline:
        if not self.periodic:
            return BSpline(self.knots, self.control_points, self.degree)
        t = unclamped_periodic(self.count, self.degree)
        return BSpline(t, wrapped_poles(self.control_points, self.degree), self.degree, extrapolate="periodic")

    def __call__(self, u: np.ndarray, nu: int = 0) -> np.ndarray:
        """(m, 3) points (or derivatives of order ``nu``) at parameters ``u`` in [0, 1]."""
        u = np.asarray(u, dtype=np.float64)
        if self.periodic:
            u = np.mod(u, 1.0)
        return self._spline(u, nu=nu)

    @property
    def count(self) -> int:
        return int(len(self.control_points))

    def transformed(self, matrix: np.ndarray, offset: np.ndarray) -> BSplineCurve:
        """The same curve under the affine map x -> x @ matrix + offset (exact for B-splines)."""
        return BSplineCurve(self.control_points @ matrix + offset, self.knots, self.degree, self.periodic)


def centripetal_parameters(points: np.ndarray, closed: bool) -> np.ndarray:
    """Parameters in [0, 1] (open: both ends; closed: [0, 1)) spaced by sqrt of chord length."""
    diffs = np.diff(points, axis=0)
    if closed:
        diffs = np.vstack([diffs, points[:1] - points[-1:]])
    steps = np.sqrt(np.linalg.norm(diffs, axis=1))
    if steps.sum() <= 0:
        raise FitError("curve points are all coincident")
    cum = np.concatenate([[0.0], np.cumsum(steps)])
    cum /= cum[-1]
    return cum[:-1] if closed else cum


def averaged_knots(u: np.ndarray, count: int, degree: int) -> np.ndarray:
    """Clamped knot vector for a least-squares fit of ``count`` control points (NURBS Book eq. 9.68-9.69)."""
    m = len(u) - 1
    n = count - 1
    d = (m + 1) / (n - degree + 1)
    j = np.arange(1, n - degree + 1)
    i = np.floor(j * d).astype(int)
    alpha = j * d - i
    interior = (1.0 - alpha) * u[i - 1] + alpha * u[i]
    return np.concatenate([np.zeros(degree + 1), interior, np.ones(degree + 1)])


def _fairness(count: int, periodic: bool) -> sparse.csr_matrix:
    """D^T D for the second differences of the control polygon (wrapping round when periodic)."""
    if periodic:
        eye = sparse.identity(count, format="csr")
        diff = (eye - 2 * sparse.csr_matrix(np.roll(np.eye(count), 1, axis=1))
                + sparse.csr_matrix(np.roll(np.eye(count), 2, axis=1)))
    else:
        diff = sparse.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(count - 2, count))
    return (diff.T @ diff).tocsr()


def _solve(a: sparse.csr_matrix, points: np.ndarray, weights: np.ndarray, fairness: sparse.csr_matrix) -> np.ndarray:
    """Weighted least squares with fairness: (A^T W A + F) P = A^T W X. Dense: a curve has at most a
    few hundred control points, where scipy.sparse's set-up costs more than the whole dense solve."""
    return solve_dense(*normal_equations(a.toarray(), weights, points, fairness.toarray()))


def _solve_tangent_distance(
    a: sparse.csr_matrix,
    points: np.ndarray,
    tangents: np.ndarray,
    weights: np.ndarray,
    fairness: sparse.csr_matrix,
    tangential: float = 0.1,
) -> np.ndarray:
    """One tangent-distance step (Wang, Pottmann & Liu 2006, "Fitting B-spline curves to point clouds by
    curvature-based squared distance minimization", ACM TOG 25(2)): errors are measured across the
    curve at each foot point, plus ``tangential`` times along it, so the fit converges in a few
    steps where plain parameter correction crawls. Dense 3n x 3n system (see ``_solve``)."""
    coo = a.tocoo()
    m, n = a.shape
    order = np.lexsort((coo.col, coo.row))
    per_row = coo.nnz // m
    if per_row * m != coo.nnz:
        raise FitError("design matrix rows do not all have degree + 1 entries")
    cols = coo.col[order].reshape(m, per_row)
    vals = coo.data[order].reshape(m, per_row)
    outer = np.einsum("ir,ic->irc", tangents, tangents)
    metric = (np.eye(3)[None] - (1.0 - tangential**2) * outer) * weights[:, None, None]
    # Block (j, k) of the normal matrix gathers N_j N_k M_i over the points i.
    data = np.einsum("ij,ik,irc->ijkrc", vals, vals, metric)
    rows = 3 * cols[:, :, None, None, None] + np.arange(3)[None, None, None, :, None]
    columns = 3 * cols[:, None, :, None, None] + np.arange(3)[None, None, None, None, :]
    shape = (m, per_row, per_row, 3, 3)
    flat = (np.broadcast_to(rows, shape) * (3 * n) + np.broadcast_to(columns, shape)).ravel()
    system = np.bincount(flat, data.ravel(), minlength=(3 * n) ** 2).reshape(3 * n, 3 * n)
    system += np.kron(fairness.toarray(), np.eye(3))
    mx = np.einsum("irc,ic->ir", metric, points)
    rhs = np.zeros((n, 3))
    np.add.at(rhs, cols.ravel(), (vals[:, :, None] * mx[:, None, :]).reshape(-1, 3))
    return solve_dense(system, rhs.ravel()).reshape(n, 3)


def densified(points: np.ndarray, minimum: int, closed: bool) -> np.ndarray:
    """The same polyline with every segment split evenly until it has at least ``minimum`` points.

    A coarse mesh gives few section points; the polyline between them is
    still the raw curve, and a least-squares fit needs samples in every span.
    """
    if len(points) < 2:
        raise FitError(f"a section of {len(points)} point(s) is not a curve")
    if len(points) >= minimum:
        return points
    pieces = int(np.ceil(minimum / len(points)))
    ends = np.vstack([points[1:], points[:1]]) if closed else points[1:]
    starts = points[: len(ends)]
    t = np.arange(pieces) / pieces
    inner = (starts[:, None, :] + t[None, :, None] * (ends - starts)[:, None, :]).reshape(-1, 3)
    return inner if closed else np.vstack([inner, points[-1:]])


@dataclass(frozen=True)
class CurveFit:
    """A fitted curve with its accuracy against the points it was fitted to (mm)."""

    curve: BSplineCurve
    max_deviation_mm: float
    rms_deviation_mm: float
    parameters: np.ndarray
    outliers: int


def fit_curve(
    points: np.ndarray,
    count: int | None = None,
    *,
    periodic: bool,
    knots: np.ndarray | None = None,
    params: np.ndarray | None = None,
    degree: int = 3,
    corrections: int = 4,
    correct_parameters: bool = True,
    tangent_steps: int = 3,
    pin_ends: bool = True,
    tangent_pin_weight: float = 1e6,
    outlier_mm: float | None = 1.0,
    fairness: float = 1e-4,
) -> CurveFit:
    """Least-squares B-spline with ``count`` control points (or on ``knots``) through ``points`` (m, 3).

    The fit alternates point-distance solves with parameter correction
    (``corrections`` projections of the points onto the curve; NURBS Book
    9.4.1), then takes ``tangent_steps`` tangent-distance steps, each kept
    only if it lowers the largest distance. params : (m,) starting parameters
    (default centripetal); knots : default averaged (open, eq. 9.68-9.69) or
    uniform (periodic); without ``params``, too few points are first densified
    (:func:`densified`). With ``correct_parameters`` False the parameters stay
    as given: one solve, and every tangent step is kept.
    pin_ends : open curves interpolate their end points, closed ones their
    start point (u = 0), with weight 1e8 in the point-distance solves and
    ``tangent_pin_weight`` in the tangent steps. Points farther than
    ``outlier_mm`` and 6 robust standard deviations from a fit (peaks from
    holes and artefacts; None: no outlier test) are dropped and the curve
    refitted, bridging them smoothly (up to two rounds); the number dropped
    is reported. A light second-difference fairness term (``fairness`` times
    the mean number of points per control point) keeps spans without data
    (bridged gaps) well posed.
    """
    if count is None:
        if knots is None:
            raise ValueError("fit_curve: give the control-point count or the knots")
        count = len(knots) - 1 if periodic else len(knots) - degree - 1
    points = np.asarray(points, dtype=np.float64)
    if params is None:
        points = densified(points, 4 * count, closed=periodic)
    elif len(params) != len(points):
        raise ValueError(f"fit_curve: {len(params)} parameters for {len(points)} points")
    pinned = ([0] if periodic else [0, -1]) if pin_ends else []
    reset = (0.0,) if periodic else (0.0, 1.0)
    dropped = 0
    for round_ in range(3 if outlier_mm is not None else 1):
        u = centripetal_parameters(points, closed=periodic) if params is None else np.array(params, dtype=np.float64)
        if knots is not None:
            fit_knots = knots
        else:
            fit_knots = periodic_knots(count) if periodic else averaged_knots(u, count, degree)
        weights = np.ones(len(points))
        weights[pinned] = 1e8
        fair = fairness * (len(points) / count) * _fairness(count, periodic)
        for _ in range(corrections + 1 if correct_parameters else 1):
            a = design_matrix(u, fit_knots, degree, periodic, count)
            curve = BSplineCurve(_solve(a, points, weights, fair), fit_knots, degree, periodic)
            if correct_parameters:
                u = project_to_curve(curve, points, u)
                u[pinned] = reset[: len(pinned)]
        residual = np.linalg.norm(curve(u) - points, axis=1)
        if outlier_mm is None:
            break
        med = np.median(residual)
        mad = 1.4826 * np.median(np.abs(residual - med))
        outlier = residual > max(outlier_mm, med + 6.0 * mad)
        outlier[pinned] = False
        if round_ == 2 or not outlier.any():
            break
        # Drop the peaks and fit the rest afresh: new parameters bridge the gap smoothly.
        points = points[~outlier]
        params = None if params is None else params[~outlier]
        dropped += int(outlier.sum())
    weights = np.ones(len(points))
    weights[pinned] = tangent_pin_weight
    best = (float(residual.max()), curve, u)
    for _ in range(tangent_steps):
        tangents = curve(u, 1)
        tangents /= np.maximum(np.linalg.norm(tangents, axis=1, keepdims=True), 1e-300)
        a = design_matrix(u, fit_knots, degree, periodic, count)
        curve = BSplineCurve(_solve_tangent_distance(a, points, tangents, weights, fair), fit_knots, degree, periodic)
        if correct_parameters:
            u = project_to_curve(curve, points, u)
            u[pinned] = reset[: len(pinned)]
        worst = float(np.linalg.norm(curve(u) - points, axis=1).max())
        if worst < best[0] or not correct_parameters:
            best = (worst, curve, u)
    worst, curve, u = best
    residual = np.linalg.norm(curve(u) - points, axis=1)
    return CurveFit(
        curve=curve,
        max_deviation_mm=float(residual.max()),
        rms_deviation_mm=float(np.sqrt(np.mean(residual**2))),
        parameters=u,
        outliers=dropped,
    )
