"""The NURBS baseline's surfaces to OpenCascade faces and back.

numpy surfaces -> Geom_BSplineSurface faces, and back; the fill-hole patch
(BRepFill_Filling, G1 to its neighbour along the apex ring). Sewing, checks
and named STEP/IGES are shared with the T-spline model (``bonecad.occ.brep``).
"""
from __future__ import annotations

import numpy as np
from OCP.BRep import BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Curve
from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace
from OCP.BRepFill import BRepFill_Filling
from OCP.Geom import Geom_BSplineSurface
from OCP.GeomAbs import GeomAbs_G1
from OCP.TColStd import TColStd_Array1OfInteger, TColStd_Array1OfReal
from OCP.TopoDS import TopoDS_Face, TopoDS_Shape

from bonecad.splines.curve import BSplineCurve
from bonecad.errors import FitError, KernelError
from bonecad.occ.brep import array1, edges, pole_grid, read_array1, real_grid
from bonecad.splines.knots import multiplicities
from bonecad.splines.surface import BSplineSurface

def _knots_and_mults(knots: np.ndarray, periodic: bool) -> tuple[list[float], list[int]]:
    if periodic:
        return [float(k) for k in knots], [1] * len(knots)
    values, counts = multiplicities(knots)
    return [float(v) for v in values], [int(c) for c in counts]


def to_geom_surface(surface: BSplineSurface) -> Geom_BSplineSurface:
    """An exact Geom_BSplineSurface of ``surface`` (periodic directions stay periodic, single knots;
    weights kept; the whole knot domain, whatever ``surface.bounds``)."""
    poles = pole_grid(surface.poles)
    weights = () if surface.weights is None else (real_grid(surface.weights),)
    uk, um = _knots_and_mults(surface.knots_u, surface.periodic_u)
    vk, vm = _knots_and_mults(surface.knots_v, surface.periodic_v)
    try:
        return Geom_BSplineSurface(
            poles,
            *weights,
            array1(uk, TColStd_Array1OfReal),
            array1(vk, TColStd_Array1OfReal),
            array1(um, TColStd_Array1OfInteger),
            array1(vm, TColStd_Array1OfInteger),
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
        seq = np.repeat(read_array1(knots), read_array1(mults, int))
        return (seq - seq[0]) / (seq[-1] - seq[0])

    return BSplineSurface(poles, full(geom.UKnots(), geom.UMultiplicities(), nu),
                          full(geom.VKnots(), geom.VMultiplicities(), nv), geom.UDegree(), geom.VDegree(),
                          region=region, reversed=reversed_)


def from_face(face: TopoDS_Face, region: str, *, reversed_: bool = False) -> BSplineSurface:
    """The numpy surface of a face lying on a non-periodic polynomial B-spline (:func:`from_geom_surface`)."""
    return from_geom_surface(BRep_Tool.Surface_s(face), region, reversed_=reversed_)


def make_face(surface: BSplineSurface, *, tolerance_mm: float = 1e-7) -> TopoDS_Face:
    """A face on the whole surface (natural bounds; a collapsed pole row becomes a degenerate edge)."""
    maker = BRepBuilderAPI_MakeFace(to_geom_surface(surface), tolerance_mm)
    if not maker.IsDone():
        raise KernelError(f"OpenCascade could not make the {surface.region} face (error {maker.Error()})")
    return maker.Face()


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


