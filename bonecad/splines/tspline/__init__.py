"""Cubic T-splines: T-mesh, blending functions, analysis-suitability, local
refinement, Bezier extraction, JSON, the ``.tsm`` format (``read_tspline``,
``write_tspline``; documents in ``tsm``), open regions. Pure numpy/scipy; ``bonecad.occ.tspline``
is the one module that converts to OpenCascade (import it explicitly).
"""
from bonecad.splines.tspline.extraction import BezierExtraction, extract
from bonecad.splines.tspline.refine import (KnotSegment, Refinement, Removal, insert_segments, refine_elements,
                                            remove_segments)
from bonecad.splines.tspline.serialize import from_dict, load, save, to_dict
from bonecad.splines.tspline.suitability import SuitabilityReport, TJunctions, check_suitability, t_junctions
from bonecad.splines.tspline.tmesh import TMesh
from bonecad.splines.tspline.tspline import TSpline
from bonecad.splines.tspline.region import open_region
from bonecad.splines.tspline.tsm import TSMDocument, TSMError, read_tspline, write_tspline

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
    "write_tspline",
]
