"""What an implant designer does first with a bone model, in OpenCascade: offset, shell, cut, drill, section.

Each operation runs on a closed solid (typically re-read from bonecad's STEP,
:func:`bonecad.occ.exchange.read_named_step`) and is judged by what it must
produce, not by OpenCascade's "done" alone (DESIGN.md: a result can pass
BRepCheck and still be wrong):

- **offset** (``BRepOffsetAPI_MakeOffsetShape``, arc joins): one valid solid
  whose volume grows by the area times the distance (Steiner: the curvature
  term is a few per cent for a 1 mm offset of a tibia);
- **thick solid**: the bone's closed shell thickened inwards into a wall
  (``BRepOffset_MakeOffset`` with thickening; ``BRepOffsetAPI_MakeThickSolid``
  returns the plain offset of a closed solid when no face is removed, and
  cannot open the T-spline at its apex cap, which is tangent to the tube): one
  valid solid of two shells whose volume is the area times the wall;
- **osteotomy**: the solid cut by a half-space (``BRepPrimAPI_MakeHalfSpace``,
  ``BRepAlgoAPI_Cut`` and ``BRepAlgoAPI_Common``) at mid-length across the long
  axis: two valid solids whose volumes add up to the bone's;
- **drill**: a cylinder cut across the shaft through the mid-length section's
  centroid: one valid solid that lost the cylinder's volume inside the bone
  (radius squared times pi times the chord the drill axis cuts);
- **section**: the solid cut by the mid-length plane (``BRepAlgoAPI_Section``):
  closed wires only.

The long axis is the solid's axis of least inertia; mid-length is the middle of
the solid's extent along it. All lengths in mm, volumes in mm^3.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from OCP.BRepAlgoAPI import BRepAlgoAPI_Common, BRepAlgoAPI_Cut, BRepAlgoAPI_Section
from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace
from OCP.BRepGProp import BRepGProp
from OCP.BRepIntCurveSurface import BRepIntCurveSurface_Inter
from OCP.BRepOffset import BRepOffset_MakeOffset, BRepOffset_Skin
from OCP.BRepOffsetAPI import BRepOffsetAPI_MakeOffsetShape
from OCP.BRepPrimAPI import BRepPrimAPI_MakeCylinder, BRepPrimAPI_MakeHalfSpace
from OCP.BRep import BRep_Builder, BRep_Tool
from OCP.GeomAbs import GeomAbs_Arc
from OCP.GProp import GProp_GProps
from OCP.ShapeAnalysis import ShapeAnalysis_FreeBounds
from OCP.TopAbs import TopAbs_SHELL, TopAbs_SOLID
from OCP.TopTools import TopTools_HSequenceOfShape
from OCP.TopoDS import TopoDS, TopoDS_Shape, TopoDS_Shell, TopoDS_Solid
from OCP.gp import gp_Ax2, gp_Dir, gp_Lin, gp_Pln, gp_Pnt

from bonecad.errors import KernelError
from bonecad.occ.brep import _subshapes, area_mm2, edges, faces, is_valid, volume_mm3

#: Tolerance handed to the offset algorithms (mm).
OFFSET_TOLERANCE_MM = 1e-3
#: How far an offset's or a wall's volume may stray from area x distance (relative): the
#: curvature term of a 1 mm offset of a tibia is +3 % (Steiner: mean curvature integral
#: ~1500 mm against 45000 mm^2 of area, LHDL's T-spline) to -3.5 % (ICL's wrinkled MRI
#: NURBS).
STEINER_SLACK = 0.10
#: Chordal deflections (mm) of the two triangulations whose volumes, extrapolated linearly to
#: zero deflection, measure an offset's volume. The gain of a 1 mm offset over area x distance,
#: triangulated at 1.0/0.5/0.25/0.1 mm: phantom T-spline 0.803/0.918/0.976/1.010, phantom NURBS
#: 0.838/0.926/0.980/1.013, ICL NURBS 0.903/0.963/0.967/0.967: the shortfall is linear in the
#: deflection, and the line through 0.5 and 0.25 gives the 0.1 mm figures within 0.25 %. At 0.1 mm
#: BRepMesh did not finish in 30 min on JIA's (wrinkled MRI) NURBS offset; 0.5 and 0.25 take 18 s
#: and ~60 s there.
OFFSET_VOLUME_DEFLECTIONS_MM = (0.5, 0.25)
#: How far the drilled-out volume may stray from pi r^2 x chord (relative): the
#: chord varies across the drill's width where the wall is curved (~2 % on a shaft).
DRILL_SLACK = 0.05
#: The osteotomy's halves must add up to the whole within this (relative).
VOLUME_BALANCE = 1e-4


@dataclass(frozen=True)
class CadOperation:
    """One operation on a solid: whether it gave what it must (``problem`` says why not), its time (s)
    and figures (mm, mm^2, mm^3)."""

    name: str
    passed: bool
    seconds: float
    figures: dict = field(default_factory=dict)
    problem: str = ""

    def to_dict(self) -> dict:
        return {"name": self.name, "passed": self.passed, "seconds": round(self.seconds, 3),
                "figures": {k: (round(v, 6) if isinstance(v, float) else v) for k, v in self.figures.items()},
                "problem": self.problem}


@dataclass(frozen=True)
class LongAxis:
    """The solid's long axis: the mid-length point, the axis (unit), a cross direction (unit, the axis
    of greatest inertia) and the length along the axis (mm)."""

    middle: np.ndarray
    direction: np.ndarray
    across: np.ndarray
    length_mm: float


def solids(shape: TopoDS_Shape) -> list:
    return _subshapes(shape, TopAbs_SOLID, TopoDS.Solid_s)


def _xyz(p) -> np.ndarray:
    return np.array([p.X(), p.Y(), p.Z()])


def long_axis(shape: TopoDS_Shape) -> LongAxis:
    """The axis of least inertia through the centre of mass, and the solid's extent along it."""
    props = GProp_GProps()
    BRepGProp.VolumeProperties_s(shape, props, 1e-6, True)
    principal = props.PrincipalProperties()
    moments = principal.Moments()
    axes = [principal.FirstAxisOfInertia(), principal.SecondAxisOfInertia(), principal.ThirdAxisOfInertia()]
    order = np.argsort(moments)
    direction = _xyz(axes[order[0]])
    across = _xyz(axes[order[2]])
    centre = _xyz(props.CentreOfMass())
    from OCP.Bnd import Bnd_Box
    from OCP.BRepBndLib import BRepBndLib

    # the extent along the axis: the tight box of the shape in a frame whose z is the axis
    box = Bnd_Box()
    BRepBndLib.AddOptimal_s(_in_frame(shape, centre, direction, across), box, False, False)
    _, _, z0, _, _, z1 = box.Get()
    return LongAxis(centre + 0.5 * (z0 + z1) * direction, direction, across, float(z1 - z0))


def _in_frame(shape: TopoDS_Shape, origin: np.ndarray, z: np.ndarray, x: np.ndarray) -> TopoDS_Shape:
    """``shape`` moved into the frame at ``origin`` with axes ``x`` and ``z`` (a copy-free relocation)."""
    from OCP.gp import gp_Ax3, gp_Trsf

    trsf = gp_Trsf()
    trsf.SetTransformation(gp_Ax3(gp_Pnt(*origin), gp_Dir(*z), gp_Dir(*x)))
    return shape.Moved(_location(trsf))


def _location(trsf):
    from OCP.TopLoc import TopLoc_Location

    return TopLoc_Location(trsf)


def _timed(name: str, fn) -> CadOperation:
    """Run ``fn() -> (passed, figures, problem)``; an OpenCascade exception is a failed operation."""
    start = time.perf_counter()
    try:
        passed, figures, problem = fn()
    except (KernelError, RuntimeError, ValueError) as exc:  # OCP raises Standard_Failure as RuntimeError
        passed, figures, problem = False, {}, f"{type(exc).__name__}: {exc}"
    except Exception as exc:  # noqa: BLE001 - Standard_Failure subclasses are not all RuntimeErrors
        passed, figures, problem = False, {}, f"OpenCascade: {type(exc).__name__}: {exc}"
    return CadOperation(name, passed, time.perf_counter() - start, figures, problem)


def _one_valid_solid(shape: TopoDS_Shape, what: str) -> TopoDS_Shape:
    found = solids(shape)
    if len(found) != 1:
        raise KernelError(f"{what} gave {len(found)} solids, not one")
    if not is_valid(found[0]):
        raise KernelError(f"{what} gave an invalid solid (BRepCheck_Analyzer)")
    return found[0]


def offset_shape(shape: TopoDS_Shape, distance_mm: float) -> TopoDS_Shape:
    """``shape`` offset by ``distance_mm`` (outwards > 0), arc joins; KernelError naming OpenCascade's error."""
    maker = BRepOffsetAPI_MakeOffsetShape()
    maker.PerformByJoin(shape, distance_mm, OFFSET_TOLERANCE_MM, BRepOffset_Skin, False, False, GeomAbs_Arc, False)
    if not maker.IsDone():
        raise KernelError(f"offset by {distance_mm} mm failed: {maker.MakeOffset().Error().name}")
    return maker.Shape()


def thicken(shape: TopoDS_Shape, thickness_mm: float) -> TopoDS_Shape:
    """A face or shell thickened into a solid ``thickness_mm`` thick (along its normal when > 0; a closed
    shell gives a solid with a wall: the shell and its offset)."""
    maker = BRepOffset_MakeOffset()
    maker.Initialize(shape, thickness_mm, OFFSET_TOLERANCE_MM, BRepOffset_Skin, False, False, GeomAbs_Arc, True,
                     False)
    maker.MakeOffsetShape()
    if not maker.IsDone():
        raise KernelError(f"thickening by {thickness_mm} mm failed: {maker.Error().name}")
    walls = solids(maker.Shape())
    if shape.ShapeType() != TopAbs_SHELL or len(walls) != 1 or len(shells(walls[0])) != 2:
        return maker.Shape()
    return _wall_in_input_order(shape, walls[0], maker.OffsetFacesFromShapes())


def _wall_in_input_order(shell: TopoDS_Shape, wall: TopoDS_Shape, images) -> TopoDS_Shape:
    """The two-shell ``wall`` rebuilt as the input ``shell`` then its offset, whose faces follow the order
    of the faces they were offset from (``images``: BRepOffset's face images).

    BRepOffset orders the offset shell's faces by a map hashed on memory addresses, and BRepCheck's solid
    check decides which shell is the cavity by a ray from that shell's first face: on ICL's T-spline the
    same STEP gave "EnclosedRegion" in 2 of 12 runs, always when one face came first. In a fixed order
    the same input gives the same solid, and the same verdict, every run.
    """
    inputs = faces(shell)
    generated = [(image, index) for index, face in enumerate(inputs) for image in images.Image(face)]
    outer, offset = sorted(shells(wall), key=lambda s: not any(f.IsSame(inputs[0]) for f in faces(s)))

    def order(face) -> int:
        found = [index for image, index in generated if face.IsSame(image)]
        if len(found) != 1:
            raise KernelError("the thick solid has an offset face that no input face generated")
        return found[0]

    builder = BRep_Builder()
    inner, rebuilt = TopoDS_Shell(), TopoDS_Solid()
    builder.MakeShell(inner)
    for face in sorted(faces(offset), key=order):  # each as the solid sees it: the new shell is forward
        builder.Add(inner, face)
    inner.Closed(True)
    builder.MakeSolid(rebuilt)
    builder.Add(rebuilt, outer)
    builder.Add(rebuilt, inner)
    return rebuilt


def _half_space(point: np.ndarray, normal: np.ndarray):
    """The half-space on the ``normal`` side of the plane through ``point``."""
    plane = BRepBuilderAPI_MakeFace(gp_Pln(gp_Pnt(*point), gp_Dir(*normal))).Face()
    return BRepPrimAPI_MakeHalfSpace(plane, gp_Pnt(*(point + normal))).Solid()


def _boolean(maker, what: str) -> TopoDS_Shape:
    maker.Build()
    if not maker.IsDone():
        raise KernelError(f"{what}: the boolean operation failed")
    return maker.Shape()


def halves(shape: TopoDS_Shape, point: np.ndarray, normal: np.ndarray) -> tuple[TopoDS_Shape, TopoDS_Shape]:
    """The parts of ``shape`` below and above the plane through ``point`` across ``normal``."""
    space = _half_space(point, normal)
    below = _boolean(BRepAlgoAPI_Cut(shape, space), "the half-space cut")
    above = _boolean(BRepAlgoAPI_Common(shape, space), "the half-space common")
    return below, above


def drilled(shape: TopoDS_Shape, centre: np.ndarray, direction: np.ndarray, diameter_mm: float,
            length_mm: float) -> TopoDS_Shape:
    """``shape`` minus a cylinder ``diameter_mm`` wide and ``length_mm`` long centred on ``centre``."""
    start = centre - 0.5 * length_mm * direction
    cylinder = BRepPrimAPI_MakeCylinder(gp_Ax2(gp_Pnt(*start), gp_Dir(*direction)), 0.5 * diameter_mm,
                                        length_mm).Solid()
    return _boolean(BRepAlgoAPI_Cut(shape, cylinder), "the drill")


def chord_mm(shape: TopoDS_Shape, point: np.ndarray, direction: np.ndarray) -> float:
    """Length of the line through ``point`` along ``direction`` inside the solid (sum of its in-segments)."""
    inter = BRepIntCurveSurface_Inter()
    inter.Init(shape, gp_Lin(gp_Pnt(*point), gp_Dir(*direction)), 1e-7)
    found = []
    while inter.More():
        found.append(inter.W())
        inter.Next()
    params = np.unique(np.round(found, 9))
    if len(params) % 2:
        raise KernelError(f"the drill axis crosses the surface {len(params)} times (odd: not through a solid)")
    return float(np.sum(params[1::2] - params[0::2]))


def section_wires(shape: TopoDS_Shape, point: np.ndarray, normal: np.ndarray) -> list:
    """The section of ``shape`` by the plane through ``point`` across ``normal``, its edges joined into wires."""
    section = _boolean(BRepAlgoAPI_Section(shape, gp_Pln(gp_Pnt(*point), gp_Dir(*normal)), False), "the section")
    found = edges(section)
    if not found:
        raise KernelError("the plane does not cut the solid")
    sequence = TopTools_HSequenceOfShape()
    for edge in found:
        sequence.Append(edge)
    joined = TopTools_HSequenceOfShape()
    ShapeAnalysis_FreeBounds.ConnectEdgesToWires_s(sequence, 1e-5, False, joined)
    return [TopoDS.Wire_s(joined.Value(i)) for i in range(1, joined.Length() + 1)]


def triangulated_volume_mm3(shape: TopoDS_Shape) -> float:
    """Volume of a solid from triangulations (BRepMesh at the two ``OFFSET_VOLUME_DEFLECTIONS_MM``,
    0.5 rad), extrapolated linearly to zero deflection.

    On offset surfaces (Geom_OffsetSurface) BRepGProp's adaptive integration is
    wrong by ~1 % while it reports 3e-6 (LHDL's T-spline offset by 1 mm: 399085
    mm^3 at eps 1e-6, 393575 at 1e-8; a 0.01 mm triangulation gives 395687, which
    Steiner's formula from the offset's area confirms to 2e-4 of the gain).
    BRepMesh runs on one thread: its parallel mode crashed CI once (SIGSEGV
    meshing the phantom T-spline's thick solid, whose faces share offset
    surfaces); on one thread the volumes are the same to the last digit.
    """
    from OCP.BRepMesh import BRepMesh_IncrementalMesh
    from OCP.BRepTools import BRepTools

    volumes = []
    for deflection_mm in OFFSET_VOLUME_DEFLECTIONS_MM:
        BRepTools.Clean_s(shape)
        mesher = BRepMesh_IncrementalMesh(shape, deflection_mm, False, 0.5, False)
        if not mesher.IsDone():
            raise KernelError("BRepMesh could not triangulate the shape")
        props = GProp_GProps()
        BRepGProp.VolumeProperties_s(shape, props, False, False, True)
        volumes.append(float(props.Mass()))
    (d0, d1), (v0, v1) = OFFSET_VOLUME_DEFLECTIONS_MM, volumes
    return v1 + (v1 - v0) * d1 / (d0 - d1)


def shells(shape: TopoDS_Shape) -> list:
    return _subshapes(shape, TopAbs_SHELL, TopoDS.Shell_s)


def run_cad_operations(shape: TopoDS_Shape, *, offset_mm: float = 1.0, wall_mm: float = 1.0,
                       drill_mm: float = 3.5) -> tuple[CadOperation, ...]:
    """The five operations on the closed solid ``shape`` (module doc), each with whether it passed its check."""
    solid = _one_valid_solid(shape, "the model")
    volume, area = volume_mm3(solid), area_mm2(solid)
    axis = long_axis(solid)

    def offset():
        result = _one_valid_solid(offset_shape(solid, offset_mm), "the offset")
        offset_volume = triangulated_volume_mm3(result)
        ratio = (offset_volume - volume) / (area * offset_mm)
        figures = {"volume_mm3": offset_volume, "volume_gain_over_area_x_distance": ratio}
        ok = abs(ratio - 1.0) <= STEINER_SLACK
        return ok, figures, "" if ok else f"volume grew by {ratio:.3f} x area x distance"

    def shell():
        result = _one_valid_solid(thicken(shells(solid)[0], -wall_mm), "the thick solid")
        wall_volume = triangulated_volume_mm3(result)
        ratio = wall_volume / (area * wall_mm)
        figures = {"volume_mm3": wall_volume, "volume_over_area_x_wall": ratio, "shells": len(shells(result))}
        ok = abs(ratio - 1.0) <= STEINER_SLACK and len(shells(result)) == 2
        return ok, figures, "" if ok else f"wall volume is {ratio:.3f} x area x wall ({len(shells(result))} shells)"

    def osteotomy():
        below, above = halves(solid, axis.middle, axis.direction)
        v_below = volume_mm3(_one_valid_solid(below, "the distal half"))
        v_above = volume_mm3(_one_valid_solid(above, "the proximal half"))
        balance = abs(v_below + v_above - volume) / volume
        figures = {"volume_below_mm3": v_below, "volume_above_mm3": v_above, "relative_imbalance": balance}
        ok = balance <= VOLUME_BALANCE and min(v_below, v_above) > 0
        return ok, figures, "" if ok else f"the halves add up to the whole within {balance:.2e} only"

    def section():
        found = section_wires(solid, axis.middle, axis.direction)
        closed = [bool(BRep_Tool.IsClosed_s(w)) for w in found]
        faces = [BRepBuilderAPI_MakeFace(w, True).Face() for w, c in zip(found, closed) if c]
        figures = {"wires": len(found), "closed_wires": int(sum(closed)),
                   "area_mm2": float(sum(area_mm2(f) for f in faces))}
        ok = all(closed)
        return ok, figures, "" if ok else f"{len(found) - sum(closed)} of {len(found)} section wires are open"

    def drill():
        centre = _section_centroid(solid, axis)
        chord = chord_mm(solid, centre, axis.across)
        result = _one_valid_solid(drilled(solid, centre, axis.across, drill_mm, 4.0 * chord), "the drill")
        removed = volume - volume_mm3(result)
        expected = np.pi * (0.5 * drill_mm) ** 2 * chord
        ratio = removed / expected
        figures = {"chord_mm": chord, "removed_mm3": removed, "removed_over_cylinder_in_bone": ratio}
        ok = abs(ratio - 1.0) <= DRILL_SLACK
        return ok, figures, "" if ok else f"the drill removed {ratio:.3f} x the cylinder's volume inside the bone"

    return (_timed("offset", offset), _timed("thick_solid", shell), _timed("osteotomy", osteotomy),
            _timed("drill", drill), _timed("section", section))


def _section_centroid(solid: TopoDS_Shape, axis: LongAxis) -> np.ndarray:
    """The centroid of the mid-length cross-section (the largest of its regions)."""
    best, centre = 0.0, axis.middle
    for wire in section_wires(solid, axis.middle, axis.direction):
        if not BRep_Tool.IsClosed_s(wire):
            continue
        face = BRepBuilderAPI_MakeFace(wire, True).Face()
        props = GProp_GProps()
        BRepGProp.SurfaceProperties_s(face, props, 1e-6)
        if abs(props.Mass()) > best:
            best, centre = abs(props.Mass()), _xyz(props.CentreOfMass())
    return centre
