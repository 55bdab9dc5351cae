"""Synthetic cohorts of phantom tibias with varied design parameters (issue 21's tests and benchmarks): the 20
varied phantoms of the measure tests (``varied_parameters``: every design parameter varied, slopes and
torsion too; meshed once per test session, ``conftest.varied_phantoms``), and ``phantom_parameters`` (five varied)."""
from __future__ import annotations

from dataclasses import asdict, replace

import numpy as np

from bonecad.imaging.phantom_tibia import TibiaParameters

#: the design parameters varied, with their ranges (mm)
VARIED = {"length_mm": (340.0, 400.0), "plateau_width_mm": (70.0, 82.0), "shaft_width_mm": (20.0, 25.0),
          "distal_width_mm": (46.0, 54.0), "malleolus_length_mm": (11.0, 17.0)}


def phantom_parameters(count: int, *, seed: int = 0, voxel_mm: float = 1.5) -> list[TibiaParameters]:
    """``count`` phantoms' parameters: each varied one drawn uniformly in its range (seeded)."""
    rng = np.random.default_rng(seed)
    base = TibiaParameters(voxel_mm=voxel_mm)
    return [replace(base, **{k: float(rng.uniform(lo, hi)) for k, (lo, hi) in VARIED.items()}) for _ in range(count)]


def varied(params: TibiaParameters) -> dict[str, float]:
    """The varied design parameters of a phantom (name -> mm)."""
    return {k: v for k, v in asdict(params).items() if k in VARIED}


#: the varied phantoms of the measure tests (issue 21: 20 phantoms)
PHANTOMS = 20


def varied_parameters(count: int = PHANTOMS) -> list[TibiaParameters]:
    """``count`` phantoms whose parameters span adult tibias (deterministic)."""
    rng = np.random.default_rng(21)
    u = rng.uniform(size=(count, 13))
    lerp = lambda i, lo, hi: lo + u[:, i] * (hi - lo)  # noqa: E731
    columns = dict(
        length_mm=lerp(0, 330.0, 400.0), plateau_width_mm=lerp(1, 70.0, 84.0), plateau_depth_mm=lerp(2, 46.0, 56.0),
        plateau_posterior_offset_mm=lerp(3, 5.0, 9.0), shaft_width_mm=lerp(4, 20.0, 25.0),
        shaft_depth_mm=lerp(5, 23.0, 28.0), distal_width_mm=lerp(6, 46.0, 54.0), distal_depth_mm=lerp(7, 36.0, 42.0),
        malleolus_length_mm=lerp(8, 12.0, 16.0), tuberosity_height_mm=lerp(9, 7.0, 11.0),
        medial_slope_deg=lerp(10, 0.0, 12.0), lateral_slope_deg=lerp(11, 0.0, 10.0), torsion_deg=lerp(12, 0.0, 40.0),
    )
    return [TibiaParameters(**{k: float(round(v[i], 2)) for k, v in columns.items()}) for i in range(count)]


def design(params: TibiaParameters) -> dict[str, float]:
    """The design parameters ``varied_parameters`` varies (name -> mm or degrees)."""
    return {k: v for k, v in asdict(params).items() if k != "voxel_mm"}
