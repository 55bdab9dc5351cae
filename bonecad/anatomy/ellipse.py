"""Least-squares ellipse fit of 2-D points (direct method).

Halir & Flusser (1998), "Numerically stable direct least squares fitting of
ellipses", the stable form of Fitzgibbon, Pilu & Fisher (1999).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bonecad.errors import FitError


@dataclass(frozen=True)
class Ellipse2D:
    """centre (2,), semi_axes (2,) major first (mm), major_direction (2,) unit, rms_residual_mm."""

    centre: np.ndarray
    semi_axes: np.ndarray
    major_direction: np.ndarray
    rms_residual_mm: float

    def points(self, count: int = 360) -> np.ndarray:
        """(count, 2) points on the ellipse."""
        angle = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
        major = self.major_direction
        minor = np.array([-major[1], major[0]])
        return (
            self.centre
            + np.outer(self.semi_axes[0] * np.cos(angle), major)
            + np.outer(self.semi_axes[1] * np.sin(angle), minor)
        )


def fit_ellipse(points: np.ndarray) -> Ellipse2D:
    """Fit an ellipse to (n, 2) points; FitError if they do not describe one."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 6:
        raise FitError(f"an ellipse needs at least 6 points, got {len(points)}")
    shift = points.mean(axis=0)
    scale = np.abs(points - shift).max()
    x, y = ((points - shift) / scale).T
    d1 = np.column_stack([x * x, x * y, y * y])
    d2 = np.column_stack([x, y, np.ones_like(x)])
    s1, s2, s3 = d1.T @ d1, d1.T @ d2, d2.T @ d2
    t = -np.linalg.solve(s3, s2.T)
    m = s1 + s2 @ t
    m = np.array([m[2] / 2.0, -m[1], m[0] / 2.0])
    _, vectors = np.linalg.eig(m)
    vectors = np.real(vectors)
    condition = 4.0 * vectors[0] * vectors[2] - vectors[1] ** 2
    candidates = np.flatnonzero(condition > 0)
    if len(candidates) == 0:
        raise FitError("the points do not lie on an ellipse")
    a1 = vectors[:, candidates[0]]
    a, b, c = a1
    d, e, f = t @ a1
    # Conic a x^2 + b xy + c y^2 + d x + e y + f = 0 -> centre, axes, angle.
    denominator = b * b - 4.0 * a * c
    cx = (2.0 * c * d - b * e) / denominator
    cy = (2.0 * a * e - b * d) / denominator
    value_at_centre = a * cx * cx + b * cx * cy + c * cy * cy + d * cx + e * cy + f
    eigvals, eigvecs = np.linalg.eigh(np.array([[a, b / 2.0], [b / 2.0, c]]))
    radii_sq = -value_at_centre / eigvals
    if np.any(radii_sq <= 0):
        raise FitError("the fitted conic is not an ellipse")
    radii = np.sqrt(radii_sq) * scale
    order = np.argsort(radii)[::-1]
    major = eigvecs[:, order[0]]
    centre = np.array([cx, cy]) * scale + shift
    fitted = Ellipse2D(centre, radii[order], major / np.linalg.norm(major), 0.0)
    dense = fitted.points(2048)
    distances = np.min(np.linalg.norm(points[:, None, :] - dense[None, :, :], axis=2), axis=1)
    return Ellipse2D(fitted.centre, fitted.semi_axes, fitted.major_direction, float(np.sqrt(np.mean(distances**2))))
