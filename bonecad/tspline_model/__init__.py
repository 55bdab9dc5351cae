"""The T-spline tibia model: one C2 T-spline tube skinned from the contour
curves, fitted to the polygonal model with local refinement, two apex caps,
Bezier-extracted into a closed OpenCascade solid (DESIGN.md step 5)."""
from bonecad.tspline_model.caps import ApexCap
from bonecad.splines.tspline.fit import FitResult, FitStats, FitTolerances, fit_adaptive, project_points
from bonecad.tspline_model.model import TSplineModel, build_tspline_model, write_tspline

__all__ = [
    "ApexCap",
    "FitResult",
    "FitStats",
    "FitTolerances",
    "TSplineModel",
    "build_tspline_model",
    "fit_adaptive",
    "project_points",
    "write_tspline",
]
