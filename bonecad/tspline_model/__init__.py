"""The T-spline tibia model: one C2 T-spline tube skinned from the contour
curves, fitted to the polygonal model with local refinement, two apex caps,
Bezier-extracted into a closed OpenCascade solid (DESIGN.md step 5)."""
from bonecad.tspline_model.caps import ApexCap
from bonecad.tspline_model.model import MeshNoise, TSplineModel, build_tspline_model, mesh_noise

__all__ = [
    "ApexCap",
    "MeshNoise",
    "TSplineModel",
    "build_tspline_model",
    "mesh_noise",
]
