"""B-rep assembly, checks and named export, shared by both models.

numpy arrays -> OpenCascade arrays (poles, weights, knots). Faces -> one sewn
shell (BRepBuilderAPI_Sewing) -> a solid oriented outward (the sign of its
volume), each face keeping its name; checks (BRepCheck_Analyzer, free
edges, exact volume and area by adaptive integration: DESIGN.md measured
BRepGProp's default 1 % off); STEP AP214 and IGES 5.3 files in mm with the solid
and every face named (STEP entity names, XCAF sub-shape names).
"""
from __future__ import annotations

import io
import logging
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeSolid, BRepBuilderAPI_Sewing
from OCP.BRepCheck import BRepCheck_Analyzer
from OCP.BRepGProp import BRepGProp
from OCP.GProp import GProp_GProps
from OCP.ShapeAnalysis import ShapeAnalysis_FreeBounds
from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE, TopAbs_REVERSED, TopAbs_SHELL, TopAbs_WIRE
from OCP.TopExp import TopExp_Explorer
from OCP.TColgp import TColgp_Array2OfPnt
from OCP.TColStd import TColStd_Array2OfReal
from OCP.TopoDS import TopoDS, TopoDS_Face, TopoDS_Shape
from OCP.gp import gp_Pnt

from bonecad.errors import KernelError
from bonecad.staging import staged_file

log = logging.getLogger(__name__)

#: Relative error of the adaptive volume and area integration.
VOLUME_EPS = 1e-6
#: Relative error of the volume integral whose sign orients a solid: 0.2 s for a
#: 1500-face T-spline solid (the default integration: 10 s), within 1 % of the volume.
ORIENTATION_EPS = 0.1
#: STEP and IGES header date: the same model gives the same bytes.
FIXED_TIMESTAMP = "2000-01-01T00:00:00"


def array1(values, cls):
    """A 1-based OpenCascade array of class ``cls`` (TColStd_Array1OfReal, ...) holding ``values``."""
    arr = cls(1, len(values))
    for k, v in enumerate(values, start=1):
        arr.SetValue(k, v)
    return arr


def read_array1(values, dtype=np.float64) -> np.ndarray:
    """A 1-based OpenCascade array (TColStd_Array1OfReal, ...OfInteger) as a numpy array (``list()`` on it
    is ~50x slower)."""
    return np.array([values.Value(i) for i in range(values.Lower(), values.Upper() + 1)], dtype=dtype)


def pole_grid(points: np.ndarray) -> TColgp_Array2OfPnt:
    """(m, n, 3) mm -> 1-based TColgp_Array2OfPnt (the poles of a surface)."""
    m, n, _ = np.shape(points)
    arr = TColgp_Array2OfPnt(1, m, 1, n)
    for a, row in enumerate(np.asarray(points, dtype=np.float64).tolist(), start=1):
        for b, xyz in enumerate(row, start=1):
            arr.SetValue(a, b, gp_Pnt(*xyz))
    return arr


def real_grid(values: np.ndarray) -> TColStd_Array2OfReal:
    """(m, n) -> 1-based TColStd_Array2OfReal (the weights of a surface's poles)."""
    m, n = np.shape(values)
    arr = TColStd_Array2OfReal(1, m, 1, n)
    for a, row in enumerate(np.asarray(values, dtype=np.float64).tolist(), start=1):
        for b, value in enumerate(row, start=1):
            arr.SetValue(a, b, value)
    return arr


def _subshapes(shape: TopoDS_Shape, kind, cast) -> list:
    out = []
    explorer = TopExp_Explorer(shape, kind)
    while explorer.More():
        out.append(cast(explorer.Current()))
        explorer.Next()
    return out


def edges(shape: TopoDS_Shape) -> list:
    return _subshapes(shape, TopAbs_EDGE, TopoDS.Edge_s)


def wires(shape: TopoDS_Shape) -> list:
    return _subshapes(shape, TopAbs_WIRE, TopoDS.Wire_s)


def faces(shape: TopoDS_Shape) -> list:
    """The faces of ``shape`` in explorer order (orientation as seen in the shape)."""
    return _subshapes(shape, TopAbs_FACE, TopoDS.Face_s)


def nonempty_faces(shape: TopoDS_Shape) -> list:
    """:func:`faces`; ValueError for a null shape or one without faces."""
    if shape is None or shape.IsNull():
        raise ValueError("shape is null")
    found = faces(shape)
    if not found:
        raise ValueError("shape has no faces")
    return found


def sew(
    faces: list[TopoDS_Face], *, tolerance_mm: float, closed: bool = True
) -> tuple[TopoDS_Shape, list[TopoDS_Face]]:
    """Sew faces into one shell (BRepBuilderAPI_Sewing; edges are cut where T-junctions meet them).

    Returns the shell and the given faces as they are in it (same order).
    Raises KernelError when the result is not one shell, or (``closed``) not a closed one.
    """
    sewing = BRepBuilderAPI_Sewing(tolerance_mm, True, True, True, False)
    for face in faces:
        sewing.Add(face)
    sewing.Perform()
    shell = sewing.SewedShape()
    if shell.IsNull() or shell.ShapeType() != TopAbs_SHELL:
        kind = "nothing" if shell.IsNull() else f"a shape of type {shell.ShapeType()}"
        raise KernelError(
            f"sewing {len(faces)} faces gave {kind} instead of one shell "
            f"({sewing.NbFreeEdges()} free edges, {sewing.NbMultipleEdges()} multiple edges)"
        )
    if closed and (sewing.NbFreeEdges() or sewing.NbMultipleEdges()):
        raise KernelError(
            f"the sewn shell is not closed: {sewing.NbFreeEdges()} free and {sewing.NbMultipleEdges()} multiple edges"
        )
    return shell, [TopoDS.Face_s(sewing.Modified(face)) for face in faces]


def solid_from_shell(shell: TopoDS_Shape) -> TopoDS_Shape:
    """The solid bounded by the closed ``shell``, oriented so that its volume is positive.

    The sign of a coarse volume integral (``ORIENTATION_EPS``) decides: ray
    classification of the point at infinity (BRepClass3d_SolidClassifier)
    called it inside a valid, outward T-spline solid of a refined tube, and
    turned that solid inside out. The shell's faces stay as they are, so
    names given to them still apply.
    """
    maker = BRepBuilderAPI_MakeSolid(TopoDS.Shell_s(shell))
    if not maker.IsDone():
        raise KernelError("OpenCascade could not make a solid of the sewn shell")
    solid = maker.Solid()
    if volume_mm3(solid, ORIENTATION_EPS) < 0:
        solid.Reverse()
    return solid


def named_solid(
    named_faces: list[tuple[str, TopoDS_Face]], *, tolerance_mm: float
) -> tuple[TopoDS_Shape, list[tuple[str, TopoDS_Face]]]:
    """Sew named faces into a closed shell and make an outward solid of it; (solid, its faces with their names)."""
    shell, sewn = sew([face for _, face in named_faces], tolerance_mm=tolerance_mm)
    solid = solid_from_shell(shell)
    solid_faces = faces(solid)
    names = names_in_order(solid_faces, [(name, f) for (name, _), f in zip(named_faces, sewn)])
    return solid, list(zip(names, solid_faces))


def names_in_order(shape_faces: list[TopoDS_Face], face_names) -> list[str]:
    """The name of each of ``shape_faces`` from (name, face) pairs, matched by TopoDS IsSame
    (the same face whatever its orientation)."""
    out = []
    for face in shape_faces:
        matches = [name for name, f in face_names if f.IsSame(face)]
        if len(matches) != 1:
            raise KernelError(f"a face of the shape matches {len(matches)} of the named faces")
        out.append(matches[0])
    return out


def volume_mm3(shape: TopoDS_Shape, eps: float = VOLUME_EPS) -> float:
    """Exact volume by adaptive Gauss integration over the faces (explicit tolerance)."""
    props = GProp_GProps()
    BRepGProp.VolumeProperties_s(shape, props, eps, True)
    return float(props.Mass())


def area_mm2(shape: TopoDS_Shape, eps: float = VOLUME_EPS) -> float:
    props = GProp_GProps()
    BRepGProp.SurfaceProperties_s(shape, props, eps)
    return float(props.Mass())


def is_valid(shape: TopoDS_Shape) -> bool:
    return bool(BRepCheck_Analyzer(shape).IsValid())


def free_edge_count(shape: TopoDS_Shape) -> int:
    """Edges bounding only one face (0 for a closed shell)."""
    analysis = ShapeAnalysis_FreeBounds(shape)
    return len(edges(analysis.GetClosedWires())) + len(edges(analysis.GetOpenWires()))


def face_is_reversed(face: TopoDS_Face) -> bool:
    return face.Orientation() == TopAbs_REVERSED


def xcaf_document():
    """An empty XCAF document in mm and its shape tool (automatic naming off: names are ours)."""
    from OCP.TCollection import TCollection_ExtendedString
    from OCP.TDocStd import TDocStd_Document
    from OCP.XCAFApp import XCAFApp_Application
    from OCP.XCAFDoc import XCAFDoc_DocumentTool

    doc = TDocStd_Document(TCollection_ExtendedString("MDTV-XCAF"))
    XCAFApp_Application.GetApplication_s().InitDocument(doc)
    XCAFDoc_DocumentTool.SetLengthUnit_s(doc, 0.001)
    tool = XCAFDoc_DocumentTool.ShapeTool_s(doc.Main())
    tool.SetAutoNaming_s(False)
    return doc, tool


def _xcaf_document(shape: TopoDS_Shape, name: str, face_names: list[tuple[str, TopoDS_Face]]):
    from OCP.TCollection import TCollection_ExtendedString
    from OCP.TDataStd import TDataStd_Name

    doc, tool = xcaf_document()
    label = tool.AddShape(shape, False)
    TDataStd_Name.Set_s(label, TCollection_ExtendedString(name))
    for face_name, face in face_names:
        sub = tool.AddSubShape(label, face)
        if sub.IsNull():
            raise KernelError(f"face {face_name!r} is not a sub-shape of the exported solid")
        TDataStd_Name.Set_s(sub, TCollection_ExtendedString(face_name))
    return doc


def stamp_step_header(model, name: str) -> None:
    """File name ``name``, the fixed timestamp and bonecad as the originating system in a STEP model's header."""
    from OCP.APIHeaderSection import APIHeaderSection_MakeHeader
    from OCP.TCollection import TCollection_HAsciiString

    from bonecad._version import __version__

    header = APIHeaderSection_MakeHeader(model)
    if not header.IsDone():
        header = APIHeaderSection_MakeHeader(0)
        header.Apply(model)
    header.SetName(TCollection_HAsciiString(name))
    header.SetTimeStamp(TCollection_HAsciiString(FIXED_TIMESTAMP))
    header.SetOriginatingSystem(TCollection_HAsciiString(f"bonecad {__version__}"))


def step_settings() -> None:
    """STEP output in mm."""
    from OCP.Interface import Interface_Static

    Interface_Static.SetCVal_s("write.step.unit", "MM")


def iges_settings() -> None:
    """IGES 5.3 output in mm with faces as B-rep (MSBO) entities."""
    from OCP.IGESControl import IGESControl_Controller
    from OCP.Interface import Interface_Static

    IGESControl_Controller.Init_s()
    Interface_Static.SetCVal_s("write.iges.unit", "MM")
    Interface_Static.SetIVal_s("write.iges.brep.mode", 1)


def stamp_iges_header(writer) -> None:
    """The fixed timestamp as the file's and the last change's date in an IGES writer's global section."""
    from OCP.TCollection import TCollection_HAsciiString

    date = TCollection_HAsciiString(FIXED_TIMESTAMP.replace("-", "").replace("T", ".").replace(":", ""))
    model = writer.Model()
    section = model.GlobalSection()
    section.SetDate(date)
    section.SetLastChangeDate(date)
    model.SetGlobalSection(section)


def order_name_entities(model) -> None:
    """Give an IGES model's name entities (406 form 15) a fixed order: the k-th of them names
    the k-th named entity.

    OpenCascade's XCAF writer creates them in the order of a hash map keyed by memory address,
    which changes from run to run; everything else it writes in a fixed order. The entities stay
    where they are (re-adding entities to a model costs ~1.5 ms each): their names are reassigned
    and each named entity is pointed at its new name entity. (``model.Number`` of an entity is 0
    through OCP, so entities are matched by the identity of their Python wrappers, which pybind11
    keeps one per object while they are referenced.)

    Only the layout the XCAF writer makes is reordered: each named entity has exactly one
    property, its name, and each name entity names one entity. Anything else (OpenCascade 7.9's
    ``RemoveProperty`` crashes or does nothing on an entity with several properties) is left in
    OpenCascade's order, with a warning: the file stays valid, only its order may vary.
    """
    from OCP.TCollection import TCollection_HAsciiString

    entities = [model.Entity(i) for i in range(1, model.NbEntities() + 1)]
    slots = [e for e in entities if e.TypeNumber() == 406 and e.FormNumber() == 15]
    is_slot = {id(e) for e in slots}
    named = []  # (entity, its name entity), in model order
    for entity in entities:
        if id(entity) in is_slot or not entity.NbProperties():
            continue
        found = entity.Properties()
        found.Start()
        while found.More():
            if id(found.Value()) in is_slot:
                if entity.NbProperties() != 1:
                    log.warning("IGES: an entity has a name among several properties; names left in "
                                "OpenCascade's order")
                    return
                named.append((entity, found.Value()))
            found.Next()
    if len({id(name) for _, name in named}) != len(named) or len(named) != len(slots):
        log.warning("IGES: a name entity names no entity or several; names left in OpenCascade's order")
        return
    values = [name.Value().ToCString() for _, name in named]
    for entity, old in named:
        entity.RemoveProperty(old)
    for (entity, _), slot in zip(named, slots):
        entity.AddProperty(slot)
    for slot, value in zip(slots, values):
        slot.Init(slot.NbPropertyValues(), TCollection_HAsciiString(value))


@contextmanager
def quiet():
    """Only failures from OpenCascade's console messenger while writing (it prints transfer statistics)."""
    from OCP.Message import Message, Message_Gravity

    printers = Message.DefaultMessenger_s().Printers()
    saved = [(p, p.GetTraceLevel()) for p in printers]
    for printer, _ in saved:
        printer.SetTraceLevel(Message_Gravity.Message_Fail)
    try:
        yield
    finally:
        for printer, level in saved:
            printer.SetTraceLevel(level)


def write_named_step(shape: TopoDS_Shape, path: str | Path, name: str,
                     face_names: list[tuple[str, TopoDS_Face]]) -> Path:
    """STEP AP214 in mm, atomically: the product and solid named ``name``, every face by its
    region (``ADVANCED_FACE('distal', ...)``, which STEP readers show as face names)."""
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.StepBasic import StepBasic_Product
    from OCP.STEPConstruct import STEPConstruct
    from OCP.STEPControl import STEPControl_AsIs, STEPControl_Writer
    from OCP.TCollection import TCollection_HAsciiString

    path = Path(path)
    with quiet():
        step_settings()
        writer = STEPControl_Writer()
        stamp_step_header(writer.Model(), name)
        if writer.Transfer(shape, STEPControl_AsIs) != IFSelect_RetDone:
            raise KernelError(f"OpenCascade could not translate the shape for STEP file {path}")
        # the product is the model (else OpenCascade names it after its translator and a count of the
        # shapes this process has written so far, which changes with what ran before)
        model = writer.Model()
        for index in range(1, model.NbEntities() + 1):
            entity = model.Value(index)
            if isinstance(entity, StepBasic_Product):
                entity.SetId(TCollection_HAsciiString(name))
                entity.SetName(TCollection_HAsciiString(name))
        finder = writer.WS().TransferWriter().FinderProcess()
        for item_name, item in [(name, shape), *face_names]:
            entity = STEPConstruct.FindEntity_s(finder, item)
            if entity is None:
                raise KernelError(f"no STEP entity for the {item_name!r} shape")
            entity.SetName(TCollection_HAsciiString(item_name))
        with staged_file(path) as tmp:
            if writer.Write(str(tmp)) != IFSelect_RetDone:
                raise KernelError(f"OpenCascade could not write STEP file {path}")
    return path


def write_named_iges(shape: TopoDS_Shape, path: str | Path, name: str,
                     face_names: list[tuple[str, TopoDS_Face]]) -> Path:
    """IGES 5.3 (B-rep faces, mm) with names, atomically."""
    return write_xcaf_iges(_xcaf_document(shape, name, face_names), path)


def write_xcaf_iges(doc, path: str | Path) -> Path:
    """IGES 5.3 (B-rep faces, mm) of an XCAF document, its names on the entities, atomically."""
    from OCP.IGESCAFControl import IGESCAFControl_Writer

    path = Path(path)
    iges_settings()
    writer = IGESCAFControl_Writer()
    writer.SetNameMode(True)
    if not writer.Transfer(doc):
        raise KernelError(f"OpenCascade could not translate the shapes for IGES file {path}")
    stamp_iges_header(writer)
    order_name_entities(writer.Model())
    with quiet(), staged_file(path) as tmp:
        if not writer.Write(str(tmp)):
            raise KernelError(f"OpenCascade could not write IGES file {path}")
    return path


def shape_to_bytes(shape: TopoDS_Shape) -> bytes:
    """OpenCascade's binary B-rep of ``shape`` (exact: geometry, topology and tolerances)."""
    from OCP.BinTools import BinTools

    buffer = io.BytesIO()
    BinTools.Write_s(shape, buffer)
    return buffer.getvalue()


def shape_from_bytes(data: bytes) -> TopoDS_Shape:
    """The shape of ``shape_to_bytes``; its sub-shapes come in the same explorer order."""
    from OCP.BinTools import BinTools

    shape = TopoDS_Shape()
    BinTools.Read_s(shape, io.BytesIO(data))
    if shape.IsNull():
        raise KernelError("OpenCascade read no shape from the binary B-rep")
    return shape


def pickle_named_shape(shape: TopoDS_Shape, face_names) -> tuple[bytes, list[str]]:
    """A picklable form of a shape and its (name, face) pairs (names in explorer order)."""
    return shape_to_bytes(shape), names_in_order(faces(shape), face_names)


def unpickle_named_shape(data: bytes, names: list[str]) -> tuple[TopoDS_Shape, tuple[tuple[str, TopoDS_Face], ...]]:
    """The shape and its (name, face) pairs back from ``pickle_named_shape``."""
    shape = shape_from_bytes(data)
    shape_faces = faces(shape)
    if len(shape_faces) != len(names):
        raise KernelError(f"the binary B-rep has {len(shape_faces)} faces, not {len(names)}")
    return shape, tuple(zip(names, shape_faces))

