"""NURBS baseline (DESIGN.md step 4): skinned ends, lofted shaft, apex caps, one sewn solid.

- :mod:`.loft` compatible end curves, skinning, shaft loft, ring caps (bone coordinates)
- :mod:`.model` :func:`build_nurbs` -> :class:`NurbsModel` (faces and solid through ``bonecad.occ``)
"""
from bonecad.nurbs_model.model import APEX_FILLS, FACE_NAMES, NurbsModel, build_nurbs

__all__ = ["APEX_FILLS", "FACE_NAMES", "NurbsModel", "build_nurbs"]
