"""A synthetic cohort of phantom tibias with varied design parameters (issue 21's tests and benchmarks)."""
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
