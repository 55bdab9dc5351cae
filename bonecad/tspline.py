"""The T-spline library under its public name: ``import bonecad.tspline`` or
``from bonecad.tspline import open_region``.

The same objects as ``bonecad.splines.tspline`` (where they live, in the spline kernel): T-mesh with a
periodic direction, blending functions, analysis-suitability, local refinement, Bezier extraction, JSON,
open regions, and the ``.tsm`` format (``read_tspline``/``write_tspline`` for Rhino-style open patches;
``tsm.read``, ``tsm.census`` for any ``#TS0200`` file as a document). ``bonecad.write_tsm`` writes a fitted
model as one closed Fusion cage.
"""
from __future__ import annotations

from bonecad.splines.tspline import *  # noqa: F403 (the kernel's public names, listed once there)
from bonecad.splines.tspline import __all__ as _kernel_names
from bonecad.splines.tspline import tsm

__all__ = [*_kernel_names, "tsm"]
