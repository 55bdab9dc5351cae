"""Analysis stage: how good a CAD model is, in numbers (the pictures are ``bonecad.render``'s).

Works on any tessellated CAD shape against the polygonal model (plain arrays),
so the NURBS baseline and the T-spline model share it:

- :mod:`.deviation` signed deviation both ways, statistics, banded histograms
- :mod:`.continuity` G0/G1/G2 across shared edges, knot continuity inside faces
- :mod:`.statistics` weighted statistics and histograms
- :mod:`.model` one model's analysis (``ModelReport``) from its settings
"""
