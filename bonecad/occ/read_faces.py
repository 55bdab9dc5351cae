"""OpenCascade faces read into numpy: each face's surface as a clamped
:class:`~bonecad.splines.surface.BSplineSurface` (rational, clamped, with the face's
parameter bounds), and whether a face covers its
whole parameter rectangle (then it can be gridded in parameters).
"""
from __future__ import annotations

import logging

import numpy as np
from OCP.BRep import BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Curve2d
from OCP.BRepTools import BRepTools
from OCP.Geom import Geom_BezierSurface, Geom_BSplineSurface, Geom_RectangularTrimmedSurface
from OCP.GeomAbs import GeomAbs_Line
from OCP.GeomConvert import GeomConvert
from OCP.Standard import Standard_Failure

from bonecad.occ.brep import edges, read_array1, wires
from bonecad.splines.surface import BSplineSurface, SurfaceSet
from bonecad.splines.project import project_faces

log = logging.getLogger(__name__)


def face_spline_surface(face) -> tuple[BSplineSurface | None, bool]:
    """The face's surface as a clamped BSplineSurface over the face's parameter range.

    Returns ``(surface, native)``: ``native`` is True when the face already lies on a
    Geom_BSplineSurface/Geom_BezierSurface (same parameterisation as the face), False
    when it was converted (plane, cylinder, sphere...: parameters differ from the
    face's, exact geometry). ``surface`` is None when conversion failed.
    """
    u0, u1, v0, v1 = BRepTools.UVBounds_s(face)
    surf = BRep_Tool.Surface_s(face)  # location applied
    native = False
    base = surf
    while isinstance(base, Geom_RectangularTrimmedSurface):
        base = base.BasisSurface()
    try:
        if isinstance(base, Geom_BSplineSurface):
            bs = base.Copy()
            native = True
        elif isinstance(base, Geom_BezierSurface):
            bs = GeomConvert.SurfaceToBSplineSurface_s(base)
            native = True
        else:
            bs = GeomConvert.SurfaceToBSplineSurface_s(
                Geom_RectangularTrimmedSurface(base, u0, u1, v0, v1)
            )
        if native and (bs.IsUPeriodic() or bs.IsVPeriodic()):
            bs.Segment(u0, u1, v0, v1)
        if bs.IsUPeriodic():
            bs.SetUNotPeriodic()
        if bs.IsVPeriodic():
            bs.SetVNotPeriodic()
    except Standard_Failure:
        return None, False
    knots_u = read_array1(bs.UKnotSequence())
    knots_v = read_array1(bs.VKnotSequence())
    nu, nv = bs.NbUPoles(), bs.NbVPoles()
    poles = np.empty((nu, nv, 3))
    rational = bs.IsURational() or bs.IsVRational()
    weights = np.ones((nu, nv)) if rational else None
    for i in range(1, nu + 1):
        for j in range(1, nv + 1):
            p = bs.Pole(i, j)
            poles[i - 1, j - 1] = (p.X(), p.Y(), p.Z())
            if weights is not None:
                weights[i - 1, j - 1] = bs.Weight(i, j)
    if native:
        bounds = np.array([u0, u1, v0, v1])
    else:
        bounds = np.array([knots_u[0], knots_u[-1], knots_v[0], knots_v[-1]])
    # a native face can lie on part of its surface; never step outside the spline
    bounds = np.array(
        [
            max(bounds[0], knots_u[0]),
            min(bounds[1], knots_u[-1]),
            max(bounds[2], knots_v[0]),
            min(bounds[3], knots_v[-1]),
        ]
    )
    closed = []
    for periodic, period, lo, hi in (
        (base.IsUPeriodic(), base.UPeriod if base.IsUPeriodic() else None, u0, u1),
        (base.IsVPeriodic(), base.VPeriod if base.IsVPeriodic() else None, v0, v1),
    ):
        closed.append(bool(periodic and period is not None and abs((hi - lo) - period()) <= 1e-9 * max(1.0, period())))
    return (
        BSplineSurface(poles, knots_u, knots_v, bs.UDegree(), bs.VDegree(), weights=weights, bounds=bounds,
                       closed_u=closed[0], closed_v=closed[1]),
        native,
    )


def native_to_spline_uv(face, surface: BSplineSurface, uv: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """Parameters on a converted surface for nodes given in the face's own parameters.

    The conversion keeps the parameter ranges but not the parameterisation (rational
    arcs), so the native parameters, rescaled to the spline range, are only a
    start: Gauss-Newton on the node positions gives the exact ones.
    """
    u0, u1, v0, v1 = BRepTools.UVBounds_s(face)
    b = surface.bounds
    start = np.column_stack(
        [
            b[0] + (uv[:, 0] - u0) / max(u1 - u0, 1e-300) * (b[1] - b[0]),
            b[2] + (uv[:, 1] - v0) / max(v1 - v0, 1e-300) * (b[3] - b[2]),
        ]
    )
    return project_faces(SurfaceSet([surface]), np.zeros(len(nodes), dtype=np.int64), nodes, start).uv


def is_natural(face, surface: BSplineSurface) -> bool:
    """True when ``face`` is its surface's whole parameter rectangle ``surface.bounds``.

    Rigorous test on the boundary: one wire, and every edge's p-curve is a
    straight line lying on a side of the rectangle (iso-lines; degenerate edges
    at poles included). Such a face is tessellated on a parameter grid, which
    covers it completely by construction.
    """
    u0, u1, v0, v1 = surface.bounds
    fu0, fu1, fv0, fv1 = BRepTools.UVBounds_s(face)
    tol = 1e-9 * max(1.0, abs(u1 - u0), abs(v1 - v0))
    if max(abs(fu0 - u0), abs(fu1 - u1), abs(fv0 - v0), abs(fv1 - v1)) > tol:
        return False
    if len(wires(face)) > 1:
        return False
    for edge in edges(face):
        curve = BRepAdaptor_Curve2d(edge, face)
        if curve.GetType() != GeomAbs_Line:
            return False
        a = curve.Value(curve.FirstParameter())
        b = curve.Value(curve.LastParameter())
        on_side = (
            (abs(a.X() - u0) <= tol and abs(b.X() - u0) <= tol)
            or (abs(a.X() - u1) <= tol and abs(b.X() - u1) <= tol)
            or (abs(a.Y() - v0) <= tol and abs(b.Y() - v0) <= tol)
            or (abs(a.Y() - v1) <= tol and abs(b.Y() - v1) <= tol)
        )
        if not on_side:
            return False
    return True
