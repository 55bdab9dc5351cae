"""The NURBS baseline to OpenCascade: the only module of bonecad.nurbs that imports OCP.

numpy surfaces -> Geom_BSplineSurface faces; the fill-hole patch
(BRepFill_Filling, G1 to its neighbour along the apex ring); sewing into one
shell (BRepBuilderAPI_Sewing), a solid (ShapeFix_Solid orients it outward),
checks (BRepCheck_Analyzer, free edges, exact volume by adaptive integration),
and STEP/IGES with the faces named by region (XCAF sub-shape names).
"""
from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

import numpy as np
from OCP.BRep import BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Curve
from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace, BRepBuilderAPI_MakeSolid, BRepBuilderAPI_Sewing
from OCP.BRepCheck import BRepCheck_Analyzer
from OCP.BRepFill import BRepFill_Filling
from OCP.BRepGProp import BRepGProp
from OCP.Geom import Geom_BSplineSurface
from OCP.GeomAbs import GeomAbs_G1
from OCP.gp import gp_Pnt
from OCP.GProp import GProp_GProps
from OCP.ShapeAnalysis import ShapeAnalysis_FreeBounds
from OCP.ShapeFix import ShapeFix_Solid
from OCP.TColgp import TColgp_Array2OfPnt
from OCP.TColStd import TColStd_Array1OfInteger, TColStd_Array1OfReal
from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE, TopAbs_REVERSED, TopAbs_SHELL, TopAbs_SOLID
from OCP.TopExp import TopExp_Explorer
from OCP.TopoDS import TopoDS, TopoDS_Face, TopoDS_Shape

from ..curves.bspline import BSplineCurve
from ..errors import FitError, KernelError
from ..io.output import staged_file
from .surface import BSplineSurface

#: Relative error of the adaptive volume integration (DESIGN.md: BRepGProp's default was 1 % off).
VOLUME_EPS = 1e-6


def _array1(values, cls):
    arr = cls(1, len(values))
    for k, v in enumerate(values):
        arr.SetValue(k + 1, v)
    return arr


def _knots_and_mults(knots: np.ndarray, periodic: bool) -> tuple[list[float], list[int]]:
    if periodic:
        return [float(k) for k in knots], [1] * len(knots)
    values, counts = np.unique(np.round(knots, 14), return_counts=True)
    return [float(v) for v in values], [int(c) for c in counts]


def to_geom_surface(surface: BSplineSurface) -> Geom_BSplineSurface:
    """An exact Geom_BSplineSurface of ``surface`` (periodic directions stay periodic, single knots)."""
    nu, nv = surface.shape
    poles = TColgp_Array2OfPnt(1, nu, 1, nv)
    for a in range(nu):
        for b in range(nv):
            poles.SetValue(a + 1, b + 1, gp_Pnt(*map(float, surface.poles[a, b])))
    uk, um = _knots_and_mults(surface.knots_u, surface.periodic_u)
    vk, vm = _knots_and_mults(surface.knots_v, surface.periodic_v)
    try:
        return Geom_BSplineSurface(
            poles,
            _array1(uk, TColStd_Array1OfReal),
            _array1(vk, TColStd_Array1OfReal),
            _array1(um, TColStd_Array1OfInteger),
            _array1(vm, TColStd_Array1OfInteger),
            surface.degree_u,
            surface.degree_v,
            surface.periodic_u,
            surface.periodic_v,
        )
    except Exception as exc:  # OCP raises Standard_ConstructionError subclasses
        raise KernelError(f"OpenCascade rejected the {surface.region} B-spline surface {surface.shape}: {exc}") from exc


def from_geom_surface(geom: Geom_BSplineSurface, region: str, *, reversed_: bool = False) -> BSplineSurface:
    """A non-periodic polynomial Geom_BSplineSurface as a numpy surface, parameters scaled to [0, 1]^2."""
    if geom.IsUPeriodic() or geom.IsVPeriodic():
        raise KernelError(f"{region}: expected a non-periodic surface from OpenCascade")
    if geom.IsURational() or geom.IsVRational():
        raise KernelError(f"{region}: expected a polynomial surface, OpenCascade returned a rational one")
    nu, nv = geom.NbUPoles(), geom.NbVPoles()
    poles = np.array([[[geom.Pole(a, b).X(), geom.Pole(a, b).Y(), geom.Pole(a, b).Z()]
                       for b in range(1, nv + 1)] for a in range(1, nu + 1)])

    def full(knots, mults, count):
        seq = np.repeat([knots.Value(i) for i in range(1, knots.Length() + 1)],
                        [mults.Value(i) for i in range(1, mults.Length() + 1)])
        return (seq - seq[0]) / (seq[-1] - seq[0])

    return BSplineSurface(poles, full(geom.UKnots(), geom.UMultiplicities(), nu),
                          full(geom.VKnots(), geom.VMultiplicities(), nv), geom.UDegree(), geom.VDegree(),
                          region=region, reversed=reversed_)


def make_face(surface: BSplineSurface, *, tolerance_mm: float = 1e-7) -> TopoDS_Face:
    """A face on the whole surface (natural bounds; a collapsed pole row becomes a degenerate edge)."""
    maker = BRepBuilderAPI_MakeFace(to_geom_surface(surface), tolerance_mm)
    if not maker.IsDone():
        raise KernelError(f"OpenCascade could not make the {surface.region} face (error {maker.Error()})")
    return maker.Face()


def _subshapes(shape: TopoDS_Shape, kind, cast) -> list:
    out = []
    explorer = TopExp_Explorer(shape, kind)
    while explorer.More():
        out.append(cast(explorer.Current()))
        explorer.Next()
    return out


def edges(shape: TopoDS_Shape) -> list:
    return _subshapes(shape, TopAbs_EDGE, TopoDS.Edge_s)


def faces(shape: TopoDS_Shape) -> list:
    return _subshapes(shape, TopAbs_FACE, TopoDS.Face_s)


def ring_edge(face: TopoDS_Face, ring: BSplineCurve):
    """The edge of ``face`` lying on the closed curve ``ring`` (checked at 8 points)."""
    probe = ring(np.linspace(0.0, 1.0, 8, endpoint=False))
    for edge in edges(face):
        if BRep_Tool.Degenerated_s(edge):
            continue
        curve = BRepAdaptor_Curve(edge)
        ts = np.linspace(curve.FirstParameter(), curve.LastParameter(), 17)
        pts = np.array([[p.X(), p.Y(), p.Z()] for p in (curve.Value(float(t)) for t in ts)])
        gap = np.min(np.linalg.norm(probe[:, None] - pts[None], axis=2), axis=1)
        if np.all(gap < 1e-6 + 0.5 * np.linalg.norm(pts[1] - pts[0])):
            return edge
    raise KernelError("no edge of the neighbour face lies on the apex ring")


def fill_patch(ring: TopoDS_Shape, support: TopoDS_Face, *, tolerance_mm: float) -> tuple[TopoDS_Face, float, float]:
    """Fill the hole bounded by the closed ``ring`` edge with a plate surface tangent (G1) to ``support``.

    Returns (face, G0 error mm, G1 error rad). KernelError when OpenCascade fails or
    the patch misses its boundary by more than ``tolerance_mm``.
    """
    filling = BRepFill_Filling(3, 15, 2, False, 1e-5, 0.1 * tolerance_mm, 0.01, 0.1, 8, 9)
    filling.Add(ring, support, GeomAbs_G1, True)
    try:
        filling.Build()
    except Exception as exc:  # Standard_Failure from the plate solver
        raise KernelError(f"OpenCascade could not fill the apex hole: {exc}") from exc
    if not filling.IsDone():
        raise KernelError("OpenCascade could not fill the apex hole (BRepFill_Filling not done)")
    g0, g1 = float(filling.G0Error()), float(filling.G1Error())
    if g0 > tolerance_mm:
        raise FitError(f"the apex fill patch misses its ring by {g0:.3g} mm (tolerance {tolerance_mm} mm)")
    return filling.Face(), g0, g1


def sew(named_faces: list[tuple[str, TopoDS_Face]], *, tolerance_mm: float) -> tuple[TopoDS_Shape, list[tuple[str, TopoDS_Face]]]:
    """Sew faces into one shell; returns the shell and the (name, face) pairs as they are in it."""
    sewing = BRepBuilderAPI_Sewing(tolerance_mm, True, True, True, False)
    for _, face in named_faces:
        sewing.Add(face)
    sewing.Perform()
    shell = sewing.SewedShape()
    if shell.IsNull() or shell.ShapeType() != TopAbs_SHELL:
        kind = "nothing" if shell.IsNull() else f"a shape of type {shell.ShapeType()}"
        raise KernelError(
            f"sewing {len(named_faces)} faces gave {kind} instead of one shell "
            f"({sewing.NbFreeEdges()} free edges, {sewing.NbMultipleEdges()} multiple edges)"
        )
    if sewing.NbFreeEdges() or sewing.NbMultipleEdges():
        raise KernelError(
            f"the sewn shell is not closed: {sewing.NbFreeEdges()} free and {sewing.NbMultipleEdges()} multiple edges"
        )
    return shell, [(name, TopoDS.Face_s(sewing.Modified(face))) for name, face in named_faces]


def solid_from_shell(shell: TopoDS_Shape) -> TopoDS_Shape:
    """A solid bounded by the closed shell, oriented so that its volume is positive."""
    maker = BRepBuilderAPI_MakeSolid(TopoDS.Shell_s(shell))
    if not maker.IsDone():
        raise KernelError("OpenCascade could not make a solid of the sewn shell")
    fix = ShapeFix_Solid(maker.Solid())
    fix.Perform()
    solid = fix.Solid()
    if solid.ShapeType() != TopAbs_SOLID:
        explorer = TopExp_Explorer(solid, TopAbs_SOLID)
        if not explorer.More():
            raise KernelError("ShapeFix_Solid returned no solid")
        solid = explorer.Current()
    return solid


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


def _xcaf_document(shape: TopoDS_Shape, name: str, face_names: list[tuple[str, TopoDS_Face]]):
    from OCP.TCollection import TCollection_ExtendedString
    from OCP.TDataStd import TDataStd_Name
    from OCP.TDocStd import TDocStd_Document
    from OCP.XCAFApp import XCAFApp_Application
    from OCP.XCAFDoc import XCAFDoc_DocumentTool

    doc = TDocStd_Document(TCollection_ExtendedString("MDTV-XCAF"))
    XCAFApp_Application.GetApplication_s().InitDocument(doc)
    XCAFDoc_DocumentTool.SetLengthUnit_s(doc, 0.001)
    tool = XCAFDoc_DocumentTool.ShapeTool_s(doc.Main())
    label = tool.AddShape(shape, False)
    TDataStd_Name.Set_s(label, TCollection_ExtendedString(name))
    for face_name, face in face_names:
        sub = tool.AddSubShape(label, face)
        if sub.IsNull():
            raise KernelError(f"face {face_name!r} is not a sub-shape of the exported solid")
        TDataStd_Name.Set_s(sub, TCollection_ExtendedString(face_name))
    return doc


@contextmanager
def _quiet():
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


def write_named_step(shape: TopoDS_Shape, path: str | Path, name: str, face_names: list[tuple[str, TopoDS_Face]]) -> Path:
    """STEP AP214 in mm, atomically: the product and solid named ``name``, every face by its
    region (``ADVANCED_FACE('distal', ...)``, which STEP readers show as face names)."""
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.Interface import Interface_Static
    from OCP.STEPConstruct import STEPConstruct
    from OCP.STEPControl import STEPControl_AsIs, STEPControl_Writer
    from OCP.TCollection import TCollection_HAsciiString

    path = Path(path)
    with _quiet():
        Interface_Static.SetCVal_s("write.step.unit", "MM")
        writer = STEPControl_Writer()
        if writer.Transfer(shape, STEPControl_AsIs) != IFSelect_RetDone:
            raise KernelError(f"OpenCascade could not translate the shape for STEP file {path}")
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


def write_named_iges(shape: TopoDS_Shape, path: str | Path, name: str, face_names: list[tuple[str, TopoDS_Face]]) -> Path:
    """IGES 5.3 (B-rep faces, mm) with names, atomically."""
    from OCP.IGESCAFControl import IGESCAFControl_Writer
    from OCP.IGESControl import IGESControl_Controller
    from OCP.Interface import Interface_Static

    path = Path(path)
    IGESControl_Controller.Init_s()
    Interface_Static.SetCVal_s("write.iges.unit", "MM")
    Interface_Static.SetIVal_s("write.iges.brep.mode", 1)
    doc = _xcaf_document(shape, name, face_names)
    writer = IGESCAFControl_Writer()
    writer.SetNameMode(True)
    if not writer.Transfer(doc):
        raise KernelError(f"OpenCascade could not translate the shape for IGES file {path}")
    with _quiet(), staged_file(path) as tmp:
        if not writer.Write(str(tmp)):
            raise KernelError(f"OpenCascade could not write IGES file {path}")
    return path
