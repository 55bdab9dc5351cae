"""Where a surface folds: the largest turn of its normal between neighbouring samples of each element.

A regular parametric surface's normal ``S_u x S_v`` turns by its curvature times
the distance travelled; a fold (a sheet turned back on itself) flips it across a
line where ``S_u x S_v`` vanishes, so neighbouring samples on either side have
normals more than 90 degrees apart. Sampled densely (12 x 12 an element, edges
included), a surface without folds shows turns of a few degrees; a turn above
90 degrees is a fold, since no smooth bone has a ridge tighter than the sample
spacing. The samples where the surface degenerates (``|S_u x S_v|`` below
``degenerate_share`` of the element set's median: a collapsed pole row) carry no
normal and are skipped.
"""
from __future__ import annotations

import numpy as np

#: a turn above this between neighbouring samples is a fold (degrees)
FOLD_TURN_DEG = 90.0
#: samples a side of each element: 12 found every fold the CAD-to-mesh deviation showed on the femurs of
#: issue 45 (TLEM2: 31 elements; the fold there 11 x 11 x 19 mm), at 1-2 s for a 7,000-element model
FOLD_SAMPLES = 12


def largest_turn_deg(du: np.ndarray, dv: np.ndarray, *, degenerate_share: float = 1e-3) -> np.ndarray:
    """(E,) degrees: per element, the largest angle between the normals of neighbouring samples.

    du, dv : (E, n, n, 3) partial derivatives on each element's n x n parameter grid (edges included)."""
    normal = np.cross(du, dv)
    length = np.linalg.norm(normal, axis=-1)
    regular = length > degenerate_share * max(float(np.median(length)), 1e-300)
    unit = normal / np.where(regular, length, 1.0)[..., None]
    worst = np.ones(len(du))
    for axis in (1, 2):
        a = np.take(unit, np.arange(unit.shape[axis] - 1), axis=axis)
        b = np.take(unit, np.arange(1, unit.shape[axis]), axis=axis)
        ok = np.take(regular, np.arange(regular.shape[axis] - 1), axis=axis) & np.take(
            regular, np.arange(1, regular.shape[axis]), axis=axis)
        cos = np.where(ok, np.einsum("...k,...k->...", a, b), 1.0)
        worst = np.minimum(worst, cos.reshape(len(du), -1).min(axis=1))
    return np.degrees(np.arccos(np.clip(worst, -1.0, 1.0)))


def element_grid(lo: np.ndarray, hi: np.ndarray, samples: int) -> np.ndarray:
    """(E, samples) parameters from ``lo`` to ``hi`` (each (E,)), ends included."""
    t = np.linspace(0.0, 1.0, samples)
    return lo[:, None] + (hi - lo)[:, None] * t[None, :]
