"""The T-spline library under its public name: ``import bonecad.tspline`` or
``from bonecad.tspline import open_region``.

The same objects as ``bonecad.splines.tspline`` (where they live, in the spline kernel): T-mesh with a
periodic direction, blending functions, analysis-suitability, local refinement, Bezier extraction, JSON,
open regions, and the ``.tsm`` format (``read_tspline``/``write_tspline`` for Rhino-style open patches;
``tsm.read``, ``tsm.census`` for any ``#TS0200`` file as a document). ``bonecad.write_tsm`` writes a fitted
model as one closed Fusion cage.
"""
from __future__ import annotations

from bonecad.splines.tspline import (BezierExtraction, KnotSegment, Refinement, Removal, SuitabilityReport,
                                     TJunctions, TMesh, TSMDocument, TSMError, TSpline, check_suitability, extract,
                                     from_dict, insert_segments, load, open_region, read_tspline, refine_elements,
                                     remove_segments, save, t_junctions, to_dict, tsm, write_tspline)

__all__ = [
    "BezierExtraction",
    "KnotSegment",
    "Refinement",
    "Removal",
    "SuitabilityReport",
    "TJunctions",
    "TMesh",
    "TSMDocument",
    "TSMError",
    "TSpline",
    "check_suitability",
    "extract",
    "from_dict",
    "insert_segments",
    "load",
    "open_region",
    "read_tspline",
    "refine_elements",
    "remove_segments",
    "save",
    "to_dict",
    "t_junctions",
    "tsm",
    "write_tspline",
]
