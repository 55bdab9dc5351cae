"""Analysis stage: how good a CAD model is, in numbers and in pictures.

Works on any OpenCascade shape against the polygonal model (plain arrays), so
the NURBS baseline and the T-spline model share it:

- :mod:`.deviation` signed deviation both ways, statistics, banded histograms
- :mod:`.continuity` G0/G1/G2 across shared edges, knot continuity inside faces
- :mod:`.render` offscreen images: deviation colour maps, zebra stripes
- :mod:`.report` report.json and report.html
- :mod:`.goldens` regression of deviation histograms against stored goldens
"""
from bonecad.analysis.deviation import (DeviationResult, DirectionResult, sample_surface, shape_deviation,
                                        signed_distance_to_shape)
from bonecad.analysis.statistics import DeviationStats, Histogram, band_edges, deviation_stats, histogram
from bonecad.mesh.tessellation import Tessellation, TessellationSettings
from bonecad.occ.tessellate import tessellate

__all__ = [
    "DeviationResult",
    "DirectionResult",
    "DeviationStats",
    "Histogram",
    "Tessellation",
    "TessellationSettings",
    "band_edges",
    "deviation_stats",
    "histogram",
    "sample_surface",
    "shape_deviation",
    "signed_distance_to_shape",
    "tessellate",
]
