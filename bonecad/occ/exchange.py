"""Named CAD entities to STEP/IGES: the frame's reference entities and any tree of named shapes.

A tree is ``(name, shape)`` or ``(name, [tree, ...])``; it becomes an XCAF
assembly, so CAD programs show every group and entity by its name (STEP
PRODUCT names; IGES name properties, on the entities but not on the groups). Writes go through ``staged_file`` so a
failed export leaves nothing behind; headers carry a fixed timestamp so the
same input gives the same bytes. Plain OCP: build123d is only needed to read
a file back (``read_step``), which keeps ~1.5 s of imports off every run.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from bonecad.errors import KernelError
from bonecad.staging import staged_file

Tree = tuple[str, Any]  # (name, TopoDS_Shape) or (name, [Tree, ...]); Any: OCP's shapes are untyped


def frame_entities(frame, plane_size_mm: float = 120.0) -> list[tuple[str, object]]:
    """Points, lines and planes of an AnatomicalFrame as named OCP shapes (scanner mm).

    Planes are rectangles ``plane_size_mm`` wide; the L-M and A-P planes run
    1.1 times the mechanical axis along it.
    """
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeEdge, BRepBuilderAPI_MakeFace, BRepBuilderAPI_MakeVertex
    from OCP.gp import gp_Ax3, gp_Dir, gp_Pln, gp_Pnt

    def pnt(p: np.ndarray) -> gp_Pnt:
        return gp_Pnt(*map(float, p))

    def point(p: np.ndarray):
        return BRepBuilderAPI_MakeVertex(pnt(p)).Vertex()

    def line(a: np.ndarray, b: np.ndarray):
        return BRepBuilderAPI_MakeEdge(pnt(a), pnt(b)).Edge()

    def plane(centre: np.ndarray, normal: np.ndarray, x_dir: np.ndarray, height: float):
        axes = gp_Ax3(pnt(centre), gp_Dir(*map(float, normal)), gp_Dir(*map(float, x_dir)))
        half_w, half_h = 0.5 * plane_size_mm, 0.5 * height
        return BRepBuilderAPI_MakeFace(gp_Pln(axes), -half_w, half_w, -half_h, half_h).Face()

    z = frame.proximal
    mid = 0.5 * (frame.plateau_centre + frame.plafond_centre)
    along = 1.1 * frame.mechanical_length_mm  # the L-M and A-P planes contain the axis and run along it
    femur = frame.femur
    femur_entities = [] if femur is None else [
        ("neck_axis", line(femur.neck_axis[1], femur.neck_axis[0])),
        ("medial_condyle_centre", point(femur.condyle_centres[0])),
        ("lateral_condyle_centre", point(femur.condyle_centres[1])),
        ("transepicondylar_axis", line(femur.epicondyles[0], femur.epicondyles[1])),
        ("anatomical_axis", line(femur.shaft_axis[0], femur.shaft_axis[1])),
        *((f"isb_{name}", line(femur.head.centre, femur.head.centre + 30.0 * axis))
          for name, axis in zip(("x_anterior", "y_proximal", "z_right"), femur.isb_axes)),
    ]
    # a femur's frame holds its head centre and knee centre where a tibia's holds these two
    upper, lower = ("head_centre", "knee_centre") if femur is not None else ("plateau_centre", "plafond_centre")
    return femur_entities + [
        (upper, point(frame.plateau_centre)),
        (lower, point(frame.plafond_centre)),
        ("distal_apex", point(frame.distal_apex)),
        ("proximal_apex", point(frame.proximal_apex)),
        ("mechanical_axis", line(frame.plafond_centre, frame.plateau_centre)),
        ("local_proximal_axis", line(frame.local_proximal_axis[1], frame.local_proximal_axis[0])),
        ("anterior_direction", line(frame.plafond_centre, frame.plafond_centre + 30.0 * frame.anterior)),
        ("lateral_direction", line(frame.plafond_centre, frame.plafond_centre + 30.0 * frame.lateral)),
        ("lm_plane", plane(mid, frame.lm_plane_normal, frame.anterior, along)),
        ("ap_plane", plane(mid, frame.ap_plane_normal, frame.lateral, along)),
        ("distal_region_boundary",
         plane(frame.origin + frame.distal_boundary_mm * z, z, frame.lateral, plane_size_mm)),
        ("proximal_region_boundary",
         plane(frame.origin + frame.proximal_boundary_mm * z, z, frame.lateral, plane_size_mm)),
    ]


def compound_of(tree: Tree):
    """All shapes of a tree in one TopoDS_Compound (nested like the tree)."""
    from OCP.BRep import BRep_Builder
    from OCP.TopoDS import TopoDS_Compound

    _, content = tree
    if not isinstance(content, list):
        return content
    builder, result = BRep_Builder(), TopoDS_Compound()
    builder.MakeCompound(result)
    for child in content:
        builder.Add(result, compound_of(child))
    return result


def _assembly(tree: Tree):
    """An XCAF document (mm) holding ``tree`` as a named assembly."""
    from OCP.TCollection import TCollection_ExtendedString
    from OCP.TDataStd import TDataStd_Name
    from OCP.TopAbs import TopAbs_VERTEX
    from OCP.TopLoc import TopLoc_Location

    from bonecad.occ.brep import xcaf_document

    doc, tool = xcaf_document()

    def add(node: Tree):
        name, content = node
        if isinstance(content, list):
            label = tool.NewShape()
            for child in content:
                component = tool.AddComponent(label, add(child), TopLoc_Location())
                TDataStd_Name.Set_s(component, TCollection_ExtendedString(child[0]))
        else:
            if content.ShapeType() == TopAbs_VERTEX:
                content = compound_of((name, [(name, content)]))  # STEP keeps no name on a bare vertex
            label = tool.AddShape(content, False)
        if label.IsNull():
            raise KernelError(f"OpenCascade could not add {name!r} to the export document")
        TDataStd_Name.Set_s(label, TCollection_ExtendedString(name))
        return label

    add(tree)
    tool.UpdateAssemblies()
    return doc


def write_step(tree: Tree, path: str | Path) -> Path:
    """STEP AP214 in mm, atomically: ``tree`` as a named assembly; KernelError if OpenCascade fails."""
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.STEPCAFControl import STEPCAFControl_Writer
    from OCP.STEPControl import STEPControl_AsIs

    from bonecad.occ.brep import quiet, stamp_step_header, step_settings

    path = Path(path)
    with quiet():
        step_settings()
        writer = STEPCAFControl_Writer()
        writer.SetNameMode(True)
        stamp_step_header(writer.Writer().Model(), tree[0])
        if not writer.Transfer(_assembly(tree), STEPControl_AsIs):
            raise KernelError(f"OpenCascade could not translate the shapes for STEP file {path}")
        number_occurrences(writer.Writer().Model())
        with staged_file(path) as tmp:
            if writer.Write(str(tmp)) != IFSelect_RetDone:
                raise KernelError(f"OpenCascade could not write STEP file {path}")
    return path


def number_occurrences(model) -> None:
    """Number a STEP model's assembly occurrences (NEXT_ASSEMBLY_USAGE_OCCURRENCE ids) 1, 2, ... in
    model order: OpenCascade takes them from a counter of the whole process, so a second file
    written by the same process would differ from the first."""
    from OCP.StepRepr import StepRepr_NextAssemblyUsageOccurrence
    from OCP.TCollection import TCollection_HAsciiString

    count = 0
    for index in range(1, model.NbEntities() + 1):
        entity = model.Value(index)
        if isinstance(entity, StepRepr_NextAssemblyUsageOccurrence):
            count += 1
            entity.SetId(TCollection_HAsciiString(str(count)))


def write_iges(tree: Tree, path: str | Path) -> Path:
    """IGES 5.3 (B-rep faces, mm) with entity names, atomically."""
    from bonecad.occ.brep import write_xcaf_iges

    return write_xcaf_iges(_assembly(tree), path)


def read_step(path: str | Path):
    """Read a STEP file back as a build123d Compound (names as labels)."""
    from build123d import import_step

    return import_step(str(path))


def read_named_step(path: str | Path) -> tuple[Any, list[tuple[str, Any]]]:
    """The one solid of a STEP file (as bonecad writes a model) and its faces with their STEP names
    (``ADVANCED_FACE('distal', ...)``; '' where a face has none). KernelError when the file holds no
    solid or several."""
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.STEPControl import STEPControl_Reader
    from OCP.TopAbs import TopAbs_SOLID
    from OCP.TopoDS import TopoDS

    from bonecad.occ.brep import _subshapes, faces

    reader = STEPControl_Reader()
    if reader.ReadFile(str(path)) != IFSelect_RetDone:
        raise KernelError(f"OpenCascade could not read STEP file {path}")
    reader.TransferRoots()
    found = _subshapes(reader.OneShape(), TopAbs_SOLID, TopoDS.Solid_s)
    if len(found) != 1:
        raise KernelError(f"STEP file {path} holds {len(found)} solids, not one")
    transfer = reader.WS().TransferReader()
    named = []
    for face in faces(found[0]):
        entity = transfer.EntityFromShapeResult(face, 1)
        name = entity.Name().ToCString() if entity is not None and hasattr(entity, "Name") else ""
        named.append((name, face))
    return found[0], named
