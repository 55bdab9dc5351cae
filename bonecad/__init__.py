"""bonecad: CT scans and meshes of long bones to native CAD models.

The Python API mirrors the pipeline, one function per stage; settings default
to the shipped ones (``Settings.load()``, from ``data/defaults.toml``):

    bone = bonecad.load_bone("tibia.stl")          # BoneMesh (mm)
    frame = bonecad.anatomical_frame(bone)         # AnatomicalFrame
    result = bonecad.reconstruct("tibia.stl", "out")
    ts = bonecad.tspline.read_tspline("patch.tsm")  # .tsm <-> T-spline (bonecad.tspline)
    bonecad.write_tsm(result.models["tspline"], "bone.tsm")  # the model as one closed Fusion cage

The public API is ``__all__`` below (this module's names and ``bonecad.tspline``, the T-spline library)
and ``STAGES``: the stage functions and tables a script calls beyond them. The documentation's API
reference is generated from these two lists, and ``tests/test_docs.py`` checks every entry has a docstring.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

from bonecad._version import __version__
from bonecad.anatomy import frame as _frame
from bonecad.anatomy.frame import AnatomicalFrame
from bonecad.errors import BonecadError, FitError, InputError, KernelError
from bonecad.mesh import intake as _intake
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.mesh.intake import Units
from bonecad.run.pipeline import Reconstruction, reconstruct
from bonecad.settings import Settings

if TYPE_CHECKING:
    from bonecad.imaging.phantom_tibia import TibiaParameters

logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = [
    "AnatomicalFrame",
    "BoneMesh",
    "BonecadError",
    "FitError",
    "InputError",
    "KernelError",
    "Reconstruction",
    "Settings",
    "TibiaParameters",
    "__version__",
    "anatomical_frame",
    "load_bone",
    "phantom_tibia",
    "reconstruct",
    "tspline",
    "write_tsm",
]

#: the stages themselves (pure functions of their inputs and their settings section), the exporters' entry
#: point and the tables scripts read: the public API beyond ``__all__``, as ``module:name``
STAGES = (
    "bonecad.mesh.intake:load_bone",
    "bonecad.anatomy.frame:anatomical_frame",
    "bonecad.imaging.segment:segment_bone",
    "bonecad.contours.curves:contour_curves",
    "bonecad.nurbs_model.model:build_nurbs",
    "bonecad.tspline_model.model:build_tspline_model",
    "bonecad.analysis.model:model_deviation",
    "bonecad.anatomy.morphometry:measure_tibia",
    "bonecad.analysis.shape_model:build_shape_model",
    "bonecad.export.registry:export",
    "bonecad.occ.interop:to_cadquery",
)


def load_bone(path: str | Path, *, units: Units = "auto", settings: Settings | None = None) -> BoneMesh:
    """Read, clean and check a tibia mesh; keep the tibia body (see ``bonecad.mesh.intake.load_bone``)."""
    s = settings if settings is not None else Settings.load()
    return _intake.load_bone(path, units=units, settings=s.mesh, plausible=s.units)


def anatomical_frame(bone: BoneMesh, settings: Settings | None = None) -> AnatomicalFrame:
    """The tibia's anatomical frame (see ``bonecad.anatomy.frame.anatomical_frame``)."""
    s = settings if settings is not None else Settings.load()
    return _frame.anatomical_frame(bone, settings=s.anatomy, plausible=s.units)


def phantom_tibia(params: TibiaParameters | None = None, settings: Settings | None = None) -> BoneMesh:
    """The synthetic phantom tibia (see ``bonecad.imaging.phantom_tibia``)."""
    from bonecad.imaging import phantom_tibia as _phantom

    s = settings if settings is not None else Settings.load()
    return _phantom.phantom_tibia(params or _phantom.TibiaParameters(), settings=s.mesh, plausible=s.units)


def write_tsm(model, path: str | Path) -> Path:
    """Write a ``TSplineModel`` as one closed T-spline cage for Autodesk Fusion (``.tsm``, scanner
    coordinates in cm; see ``bonecad.tspline_model.cage``)."""
    from bonecad.splines.tspline import tsm
    from bonecad.tspline_model.cage import model_cage

    return tsm.write(model_cage(model), path)


def __getattr__(name: str):
    if name == "tspline":  # the T-spline library: T-mesh, evaluation, refinement, .tsm read/write
        import importlib

        return importlib.import_module("bonecad.tspline")
    if name == "TibiaParameters":  # the CT stack (scipy.ndimage) is not imported for a mesh
        from bonecad.imaging.phantom_tibia import TibiaParameters

        return TibiaParameters
    raise AttributeError(f"module 'bonecad' has no attribute {name!r}")
