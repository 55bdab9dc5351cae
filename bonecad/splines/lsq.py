"""Linear least squares for spline fitting: weighted normal equations with a fairness term, and their solves.

A fit of control points P to values X at fixed parameters minimises
sum_i w_i |(A P)_i - X_i|^2 + P^T F P, whose normal equations are
(A^T W A + F) P = A^T W X. The matrix is symmetric positive (semi-)definite:
curves (a few hundred unknowns) solve it dense, T-splines (thousands) with a
sparse LU in symmetric mode (:func:`solve_spd`).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from bonecad.errors import FitError


def normal_equations(a, weights: np.ndarray, values: np.ndarray, fairness=None):
    """(A^T W A + F, A^T W X) for a design matrix ``a`` (m, n), dense or scipy sparse.

    weights : (m,) >= 0; values : (m, k); fairness : (n, n) like ``a`` (dense or sparse) or None.
    """
    if sp.issparse(a):
        wa = sp.diags(weights) @ a
        normal = a.T @ wa
    else:
        wa = a * weights[:, None]
        normal = wa.T @ a
    if fairness is not None:
        normal = normal + fairness
    return normal, wa.T @ values


def solve_dense(matrix: np.ndarray, rhs: np.ndarray, *, max_condition: float | None = None,
                what: str = "") -> np.ndarray:
    """``matrix`` x = ``rhs`` (dense, square). With ``max_condition``, a system whose condition
    number exceeds it (or is not finite) raises FitError naming ``what``."""
    if max_condition is not None:
        cond = np.linalg.cond(matrix)
        if not np.isfinite(cond) or cond > max_condition:
            raise FitError(f"{what}: the system is singular or ill-conditioned (condition number {cond:.3g})")
    return np.linalg.solve(matrix, rhs)


def solve_spd(normal: sp.spmatrix, rhs: np.ndarray, *, tikhonov: float = 0.0) -> np.ndarray:
    """Solution of a sparse symmetric positive definite system (one factorisation for all columns of ``rhs``).

    tikhonov : adds tikhonov x max(diag) times the identity, so that unknowns no equation
    reaches stay at 0 instead of making the matrix singular. Minimum-degree ordering on
    the symmetric pattern (about twice as fast as COLAMD on T-spline fits); diagonal
    pivots are stable for an SPD matrix, so symmetric mode keeps the ordering's fill
    (another 2x on 2000 control points). Raises FitError when singular or non-finite.
    """
    if tikhonov > 0:
        normal = normal + sp.identity(normal.shape[0]) * (tikhonov * normal.diagonal().max())
    try:
        lu = spla.splu(sp.csc_matrix(normal), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                       options={"SymmetricMode": True})
    except RuntimeError as exc:
        raise FitError(f"least-squares fit: singular normal equations ({exc})") from exc
    x = lu.solve(np.asarray(rhs))
    if not np.all(np.isfinite(x)):
        raise FitError("least-squares fit produced non-finite control points")
    return x


def least_squares(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Minimum-norm least-squares solution of a small dense, possibly rank-deficient system (SVD)."""
    return np.linalg.lstsq(a, b, rcond=None)[0]
