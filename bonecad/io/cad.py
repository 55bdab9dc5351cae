"""STEP/IGES writing and reading, and the frame's reference entities as native CAD entities.

The one place where named build123d shapes become files. Writes go through
``staged_file`` so a failed export leaves nothing behind; STEP headers carry
a fixed timestamp so the same model gives the same bytes.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import KernelError
from .output import staged_file

FIXED_TIMESTAMP = "2000-01-01T00:00:00"


def named(shape, name: str):
    """A build123d shape carrying ``name`` into STEP (vertices are wrapped, STEP drops their names)."""
    from build123d import Compound, Vertex

    if isinstance(shape, Vertex):
        shape = Compound(children=[shape])
    shape.label = name
    return shape


def frame_shapes(frame, plane_size_mm: float = 120.0) -> list:
    """Points, lines and planes of an AnatomicalFrame as named build123d shapes (scanner mm)."""
    from build123d import Edge, Face, Plane, Vertex

    def point(name: str, p: np.ndarray):
        return named(Vertex(*map(float, p)), name)

    def line(name: str, a: np.ndarray, b: np.ndarray):
        return named(Edge.make_line(tuple(map(float, a)), tuple(map(float, b))), name)

    def plane(name: str, centre: np.ndarray, normal: np.ndarray, x_dir: np.ndarray, height: float):
        pl = Plane(origin=tuple(map(float, centre)), x_dir=tuple(map(float, x_dir)), z_dir=tuple(map(float, normal)))
        return named(Face.make_rect(plane_size_mm, height, pl), name)

    z = frame.proximal
    mid = 0.5 * (frame.plateau_centre + frame.plafond_centre)
    along = 1.1 * frame.mechanical_length_mm  # the L-M and A-P planes contain the axis and run along it
    return [
        point("plateau_centre", frame.plateau_centre),
        point("plafond_centre", frame.plafond_centre),
        point("distal_apex", frame.distal_apex),
        point("proximal_apex", frame.proximal_apex),
        line("mechanical_axis", frame.plafond_centre, frame.plateau_centre),
        line("local_proximal_axis", frame.local_proximal_axis[1], frame.local_proximal_axis[0]),
        line("anterior_direction", frame.plafond_centre, frame.plafond_centre + 30.0 * frame.anterior),
        line("lateral_direction", frame.plafond_centre, frame.plafond_centre + 30.0 * frame.lateral),
        plane("lm_plane", mid, frame.lm_plane_normal, frame.anterior, along),
        plane("ap_plane", mid, frame.ap_plane_normal, frame.lateral, along),
        plane("distal_region_boundary", frame.origin + frame.distal_boundary_mm * z, z, frame.lateral, plane_size_mm),
        plane("proximal_region_boundary", frame.origin + frame.proximal_boundary_mm * z, z, frame.lateral, plane_size_mm),
    ]


def compound(shapes: Sequence, name: str):
    """One named compound of named shapes."""
    from build123d import Compound

    result = Compound(children=list(shapes))
    result.label = name
    return result


def write_step(shape, path: str | Path) -> Path:
    """Write ``shape`` (build123d) to STEP in mm, atomically; KernelError if OpenCascade fails."""
    from build123d import Unit, export_step

    path = Path(path)
    with staged_file(path) as tmp:
        if not export_step(shape, tmp, unit=Unit.MM, timestamp=FIXED_TIMESTAMP):
            raise KernelError(f"OpenCascade could not write STEP file {path}")
    return path


def write_iges(shape, path: str | Path) -> Path:
    """Write ``shape`` to IGES (5.3, B-rep faces, mm), atomically."""
    from OCP.IGESControl import IGESControl_Controller, IGESControl_Writer
    from OCP.Interface import Interface_Static

    path = Path(path)
    IGESControl_Controller.Init_s()
    Interface_Static.SetCVal_s("write.iges.unit", "MM")
    writer = IGESControl_Writer("MM", 1)
    if not writer.AddShape(shape.wrapped):
        raise KernelError(f"OpenCascade could not translate the shape for IGES file {path}")
    writer.ComputeModel()
    with staged_file(path) as tmp:
        if not writer.Write(str(tmp)):
            raise KernelError(f"OpenCascade could not write IGES file {path}")
    return path


def read_step(path: str | Path):
    """Read a STEP file back as a build123d Compound (names as labels)."""
    from build123d import import_step

    return import_step(str(path))
