"""NURBS baseline (DESIGN.md step 4): skinned ends, lofted shaft, apex caps, one sewn solid.

- :mod:`.surface` numpy B-spline surfaces and the periodic / clamped interpolation
- :mod:`.loft` compatible end curves, skinning, shaft loft, ring caps (bone coordinates)
- :mod:`.occ` the OpenCascade boundary: faces, fill-hole patch, sewing, solid, STEP/IGES
- :mod:`.model` :func:`build_nurbs` -> :class:`NurbsModel`, :func:`write_nurbs`
"""
from bonecad.nurbs_model.model import APEX_FILLS, FACE_NAMES, NurbsModel, build_nurbs, write_nurbs
from bonecad.splines.surface import BSplineSurface

__all__ = ["APEX_FILLS", "FACE_NAMES", "BSplineSurface", "NurbsModel", "build_nurbs", "write_nurbs"]
