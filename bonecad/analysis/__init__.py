"""Analysis stage: how good a CAD model is, in numbers (the pictures are ``bonecad.render``'s).

Works on any tessellated CAD shape against the polygonal model (plain arrays),
so the NURBS baseline and the T-spline model share it:

- :mod:`.deviation` signed deviation both ways, statistics, banded histograms
- :mod:`.continuity` G0/G1/G2 across shared edges, knot continuity inside faces
- :mod:`.statistics` weighted statistics and histograms
- :mod:`.model` one model's analysis (``ModelReport``) from its settings
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
