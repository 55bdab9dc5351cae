"""bonecad: CT scans and meshes of long bones to native CAD models.

The Python API mirrors the pipeline, one function per stage::

    bone = bonecad.load_bone("tibia.stl")          # BoneMesh (mm)
    frame = bonecad.anatomical_frame(bone)         # AnatomicalFrame
"""
from __future__ import annotations

import importlib

from bonecad._version import __version__

from bonecad.anatomy.frame import AnatomicalFrame, anatomical_frame
from bonecad.config import load_config
from bonecad.errors import BonecadError, FitError, InputError, KernelError
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.mesh.intake import load_bone, prepare_bone
from bonecad.run.pipeline import Reconstruction, reconstruct

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

#: imported on first use: the CT stack (scipy.ndimage) is not needed for a mesh
_LAZY = {"TibiaParameters": ".imaging.phantom_tibia", "phantom_tibia": ".imaging.phantom_tibia"}


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module 'bonecad' has no attribute {name!r}")
