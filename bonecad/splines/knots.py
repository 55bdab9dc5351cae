"""Knot vector conventions: full sequences <-> (values, multiplicities), and the periodic convention.

A clamped direction carries its full knot sequence (multiplicities repeated).
A periodic direction of ``count`` poles carries the count + 1 uniform knots of
one period, ``linspace(0, 1, count + 1)``: single knots, C2 everywhere with no
seam (OpenCascade's periodic interpolation leaves a double knot at the start).
Pole j of a periodic B-spline is the function on knots (j - degree) / count ..
(j + 1) / count, wrapping round.
"""
from __future__ import annotations

import numpy as np


def multiplicities(knots: np.ndarray, decimals: int = 14) -> tuple[np.ndarray, np.ndarray]:
    """(distinct values, multiplicities) of a full knot sequence; knots equal to ``decimals`` merge."""
    return np.unique(np.round(np.asarray(knots, dtype=np.float64), decimals), return_counts=True)


def full_sequence(values: np.ndarray, mults: np.ndarray) -> np.ndarray:
    """The full knot sequence: each value repeated by its multiplicity."""
    return np.repeat(np.asarray(values, dtype=np.float64), np.asarray(mults, dtype=np.int64))


def breakpoints(knots: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """lo, the distinct knots strictly between lo and hi, and hi: the knot spans' ends over [lo, hi]."""
    inner = np.unique(knots[(knots > lo) & (knots < hi)])
    return np.concatenate([[lo], inner, [hi]])


def periodic_knots(count: int) -> np.ndarray:
    """The count + 1 uniform knots of one period of a periodic B-spline with ``count`` poles."""
    return np.linspace(0.0, 1.0, count + 1)


def unclamped_periodic(count: int, degree: int) -> np.ndarray:
    """(count + 2 degree + 1,) unclamped uniform knots, (j - degree) / count for j = 0 .., on which
    the poles wrapped round (the first ``degree`` repeated at the end) give the periodic spline on [0, 1]."""
    return np.arange(-degree, count + degree + 1, dtype=np.float64) / count


def wrapped_poles(poles: np.ndarray, degree: int, axis: int = 0) -> np.ndarray:
    """The poles with their first ``degree`` appended along ``axis`` (see :func:`unclamped_periodic`)."""
    head = np.take(poles, np.arange(degree), axis=axis)
    return np.concatenate([poles, head], axis=axis)
