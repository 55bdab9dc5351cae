"""bonecad: CT scans and meshes of long bones to native CAD models.

The Python API mirrors the pipeline, one function per stage::

    bone = bonecad.load_bone("tibia.stl")          # BoneMesh (mm)
    frame = bonecad.anatomical_frame(bone)         # AnatomicalFrame
"""
from __future__ import annotations

__version__ = "0.1.0"

from .anatomy.frame import AnatomicalFrame, anatomical_frame
from .config import load_config
from .errors import BonecadError, FitError, InputError, KernelError
from .imaging.phantom_tibia import TibiaParameters, phantom_tibia
from .mesh.bone_mesh import BoneMesh
from .mesh.intake import load_bone, prepare_bone
from .pipeline import Reconstruction, reconstruct

__all__ = [
    "AnatomicalFrame",
    "BoneMesh",
    "BonecadError",
    "FitError",
    "InputError",
    "KernelError",
    "TibiaParameters",
    "anatomical_frame",
    "load_bone",
    "load_config",
    "phantom_tibia",
    "prepare_bone",
    "Reconstruction",
    "reconstruct",
]
