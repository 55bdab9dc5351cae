"""Cubic T-splines: T-mesh, blending functions, analysis-suitability, local
refinement, Bezier extraction, JSON. Pure numpy/scipy; ``bonecad.tspline.occ``
is the one module that converts to OpenCascade (import it explicitly).
"""
from bonecad.tspline.extraction import BezierExtraction, extract
from bonecad.tspline.refine import KnotSegment, Refinement, Removal, insert_segments, refine_elements, remove_segments
from bonecad.tspline.serialize import from_dict, load, save, to_dict
from bonecad.tspline.suitability import SuitabilityReport, TJunctions, check_suitability, t_junctions
from bonecad.tspline.tmesh import TMesh
from bonecad.tspline.tspline import SurfaceSample, TSpline

__all__ = [
    "BezierExtraction",
    "KnotSegment",
    "Refinement",
    "Removal",
    "SuitabilityReport",
    "SurfaceSample",
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
    "t_junctions",
]
