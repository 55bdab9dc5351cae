"""Area-weighted deviation statistics and banded histograms (numpy only).

The histogram is the paper's Fig. 15/16: the share of surface per deviation
band, fixed bands (``band_width_mm`` wide from ``-band_limit_mm`` to
``+band_limit_mm``, from ``[analysis]`` in the defaults) plus an underflow and
an overflow bin.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from bonecad.settings import AnalysisSettings

#: percentiles of |deviation| reported by :class:`DeviationStats`
PERCENTILES = (50.0, 90.0, 95.0, 99.0, 99.9)


@dataclass(frozen=True)
class DeviationStats:
    """Statistics of signed deviations d (mm, positive = mesh outside the CAD model).

    rms_mm, mean_mm : area-weighted root mean square and mean of d
    abs_percentiles_mm : (5,) weighted percentiles of |d| at :data:`PERCENTILES`
    max_outside_mm : largest d (>= 0 unless every point is inside)
    max_inside_mm : largest -d (>= 0 unless every point is outside)
    area_mm2 : surface area the samples stand for; count : number of samples
    """

    rms_mm: float
    mean_mm: float
    abs_percentiles_mm: np.ndarray
    max_outside_mm: float
    max_inside_mm: float
    area_mm2: float
    count: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "rms_mm": self.rms_mm,
            "mean_mm": self.mean_mm,
            "abs_percentiles_mm": {
                f"p{p:g}": float(v) for p, v in zip(PERCENTILES, self.abs_percentiles_mm)
            },
            "max_outside_mm": self.max_outside_mm,
            "max_inside_mm": self.max_inside_mm,
            "area_mm2": self.area_mm2,
            "count": self.count,
        }


@dataclass(frozen=True)
class Histogram:
    """Share of surface per deviation band.

    edges_mm : (B+1,) band edges; band i is [edges[i], edges[i+1])
    shares : (B+2,) [underflow (< edges[0]), band 0..B-1, overflow (>= edges[-1])]; sums to 1
    """

    edges_mm: np.ndarray
    shares: np.ndarray

    def labels(self) -> list[str]:
        e = self.edges_mm
        return (
            [f"< {e[0]:g}"]
            + [f"[{a:g}, {b:g})" for a, b in zip(e[:-1], e[1:])]
            + [f">= {e[-1]:g}"]
        )

    def to_dict(self) -> dict[str, Any]:
        return {"edges_mm": self.edges_mm.tolist(), "shares": self.shares.tolist()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Histogram:
        edges = np.asarray(data["edges_mm"], dtype=np.float64)
        shares = np.asarray(data["shares"], dtype=np.float64)
        if shares.shape != (len(edges) + 1,):
            raise ValueError(
                f"histogram has {len(edges)} edges and {len(shares)} shares; expected "
                f"{len(edges) + 1} shares (bands plus under- and overflow)"
            )
        return cls(edges, shares)


def settings_band_edges(settings: AnalysisSettings) -> np.ndarray:
    """The histogram band edges (mm) of the ``[analysis]`` settings."""
    return band_edges(settings.band_width_mm, settings.band_limit_mm)


def band_edges(band_width_mm: float, band_limit_mm: float) -> np.ndarray:
    """Band edges from -limit to +limit in steps of width (mm; ``[analysis]`` settings)."""
    width, limit = band_width_mm, band_limit_mm
    if width <= 0 or limit <= 0:
        raise ValueError(f"band width and limit must be > 0, got {width} and {limit}")
    count = int(round(2 * limit / width))
    if abs(count * width - 2 * limit) > 1e-9 * limit:
        raise ValueError(f"band limit {limit} mm is not a whole number of {width} mm bands")
    return np.round(np.linspace(-limit, limit, count + 1), 9)


def histogram(deviation_mm: np.ndarray, weights: np.ndarray | None, edges_mm: np.ndarray) -> Histogram:
    """Weighted share of deviations per band (``edges_mm`` from :func:`band_edges`)."""
    d = np.asarray(deviation_mm, dtype=np.float64)
    w = np.ones_like(d) if weights is None else np.asarray(weights, dtype=np.float64)
    edges = np.asarray(edges_mm, dtype=np.float64)
    if d.shape != w.shape:
        raise ValueError(f"deviation {d.shape} and weights {w.shape} differ in shape")
    if len(d) == 0 or w.sum() <= 0:
        raise ValueError("histogram of no samples (or zero total weight)")
    index = np.searchsorted(edges, d, side="right")  # 0 = underflow, len(edges) = overflow
    shares = np.bincount(index, weights=w, minlength=len(edges) + 1) / w.sum()
    return Histogram(edges, shares)


def weighted_percentiles(values: np.ndarray, weights: np.ndarray, percents) -> np.ndarray:
    """Weighted percentiles (inverse of the weighted empirical CDF, lower value)."""
    order = np.argsort(values)
    v = values[order]
    cw = np.cumsum(weights[order])
    targets = np.asarray(percents, dtype=np.float64) / 100.0 * cw[-1]
    idx = np.clip(np.searchsorted(cw, targets - 1e-12 * cw[-1], side="left"), 0, len(v) - 1)
    return v[idx]


def share_within(deviation_mm: np.ndarray, weights: np.ndarray, limit_mm: float) -> float:
    """Area share (weights: mm^2 per sample) of the samples with |deviation| <= ``limit_mm`` (mm)."""
    d = np.abs(np.asarray(deviation_mm, dtype=np.float64))
    w = np.asarray(weights, dtype=np.float64)
    return float(w[d <= limit_mm].sum() / w.sum())


def deviation_stats(deviation_mm: np.ndarray, weights: np.ndarray | None = None) -> DeviationStats:
    """Area-weighted statistics of signed deviations (weights: mm^2 each sample stands for)."""
    d = np.asarray(deviation_mm, dtype=np.float64)
    w = np.ones_like(d) if weights is None else np.asarray(weights, dtype=np.float64)
    if d.shape != w.shape or d.ndim != 1:
        raise ValueError(f"deviation {d.shape} and weights {w.shape} must be equal 1-d shapes")
    if len(d) == 0 or w.sum() <= 0:
        raise ValueError("statistics of no samples (or zero total weight)")
    total = w.sum()
    return DeviationStats(
        rms_mm=float(np.sqrt(np.sum(w * d * d) / total)),
        mean_mm=float(np.sum(w * d) / total),
        abs_percentiles_mm=weighted_percentiles(np.abs(d), w, PERCENTILES),
        max_outside_mm=float(d.max()),
        max_inside_mm=float(-d.min()),
        area_mm2=float(total),
        count=int(len(d)),
    )
