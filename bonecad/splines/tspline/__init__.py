"""Cubic T-splines: T-mesh, blending functions, analysis-suitability, local
refinement, Bezier extraction, JSON. Pure numpy/scipy; ``bonecad.occ.tspline``
is the one module that converts to OpenCascade (import it explicitly).
"""
from bonecad.splines.tspline.extraction import BezierExtraction, extract
from bonecad.splines.tspline.refine import (KnotSegment, Refinement, Removal, insert_segments, refine_elements,
                                            remove_segments)
from bonecad.splines.tspline.serialize import from_dict, load, save, to_dict
from bonecad.splines.tspline.suitability import SuitabilityReport, TJunctions, check_suitability, t_junctions
from bonecad.splines.tspline.tmesh import TMesh
from bonecad.splines.tspline.tspline import TSpline

__all__ = [
    "BezierExtraction",
    "KnotSegment",
    "Refinement",
    "Removal",
    "SuitabilityReport",
    "TJunctions",
    "TMesh",
    "TSpline",
    "check_suitability",
    "extract",
    "from_dict",
    "insert_segments",
    "load",
    "refine_elements",
    "remove_segments",
    "save",
    "to_dict",
    "t_junctions",
]
