"""T-splines to OpenCascade: the only module of bonecad.tspline that imports OCP.

- every Bezier element -> a Geom_BezierSurface (rational when the weights
  differ) -> a face; neighbours' boundary curves are computed from the same
  blending functions, so they agree up to rounding and sewing
  (BRepBuilderAPI_Sewing) joins them, cutting the long edges at T-junctions;
- a tensor-product T-spline -> one Geom_BSplineSurface (periodic in u when s is).
"""
from __future__ import annotations

import numpy as np
from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace, BRepBuilderAPI_Sewing
from OCP.BRepCheck import BRepCheck_Analyzer
from OCP.Geom import Geom_BezierSurface, Geom_BSplineSurface
from OCP.gp import gp_Pnt
from OCP.TColgp import TColgp_Array2OfPnt
from OCP.TColStd import TColStd_Array1OfInteger, TColStd_Array1OfReal, TColStd_Array2OfReal
from OCP.TopAbs import TopAbs_SHELL
from OCP.TopoDS import TopoDS_Face, TopoDS_Shape

from bonecad.errors import InputError, KernelError
from bonecad.tspline.tspline import TSpline

#: Largest relative weight spread still written as a polynomial Bezier patch.
_POLYNOMIAL_WEIGHTS = 1e-14


def _poles(points: np.ndarray) -> TColgp_Array2OfPnt:
    """(m, n, 3) float -> 1-based TColgp_Array2OfPnt."""
    m, n, _ = points.shape
    arr = TColgp_Array2OfPnt(1, m, 1, n)
    for a in range(m):
        for b in range(n):
            x, y, z = points[a, b]
            arr.SetValue(a + 1, b + 1, gp_Pnt(float(x), float(y), float(z)))
    return arr


def _weights(w: np.ndarray) -> TColStd_Array2OfReal:
    m, n = w.shape
    arr = TColStd_Array2OfReal(1, m, 1, n)
    for a in range(m):
        for b in range(n):
            arr.SetValue(a + 1, b + 1, float(w[a, b]))
    return arr


def _array1(values, cls):
    arr = cls(1, len(values))
    for k, v in enumerate(values):
        arr.SetValue(k + 1, v)
    return arr


def bezier_surfaces(ts: TSpline) -> list[Geom_BezierSurface]:
    """One bicubic (rational) Bezier surface per element, u along s, v along t.

    Each patch is parametrised on [0, 1]^2 (the element's local coordinates).
    """
    points, weights = ts.bezier_points
    out = []
    for p, w in zip(points, weights):
        if np.ptp(w) <= _POLYNOMIAL_WEIGHTS * w.max():
            out.append(Geom_BezierSurface(_poles(p)))
        else:
            out.append(Geom_BezierSurface(_poles(p), _weights(w)))
    return out


def bezier_faces(ts: TSpline, *, tolerance_mm: float = 1e-7) -> list[TopoDS_Face]:
    """One face per Bezier element (natural bounds of its patch)."""
    faces = []
    for e, surf in enumerate(bezier_surfaces(ts)):
        maker = BRepBuilderAPI_MakeFace(surf, tolerance_mm)
        if not maker.IsDone():
            raise KernelError(f"OpenCascade could not make a face of Bezier element {e} (error {maker.Error()})")
        faces.append(maker.Face())
    return faces


def sew(faces: list[TopoDS_Face], *, tolerance_mm: float = 1e-6) -> TopoDS_Shape:
    """Sew faces into one shell (BRepBuilderAPI_Sewing, edges cut at T-junctions).

    Raises KernelError when the result is not a single valid shell.
    """
    if not faces:
        raise InputError("sew: no faces given")
    sewing = BRepBuilderAPI_Sewing(tolerance_mm, True, True, True, False)
    for f in faces:
        sewing.Add(f)
    sewing.Perform()
    shape = sewing.SewedShape()
    if shape.IsNull():
        raise KernelError("OpenCascade sewing returned no shape")
    if shape.ShapeType() != TopAbs_SHELL:
        raise KernelError(
            f"sewing {len(faces)} faces gave a {shape.ShapeType()} instead of one shell "
            f"({sewing.NbFreeEdges()} free edges, {sewing.NbMultipleEdges()} multiple edges)"
        )
    return shape


def to_shell(ts: TSpline, *, tolerance_mm: float = 1e-6) -> TopoDS_Shape:
    """The T-spline as one sewn shell of Bezier faces."""
    return sew(bezier_faces(ts, tolerance_mm=0.1 * tolerance_mm), tolerance_mm=tolerance_mm)


def is_valid(shape: TopoDS_Shape) -> bool:
    """BRepCheck_Analyzer's verdict on a shape."""
    return bool(BRepCheck_Analyzer(shape).IsValid())


def bspline_surface(ts: TSpline) -> Geom_BSplineSurface:
    """A tensor-product T-spline as one Geom_BSplineSurface (u = s, v = t).

    Raises InputError when the T-mesh has T-junctions (not a tensor product).
    """
    mesh = ts.mesh
    if not (mesh.s_edges.all() and mesh.t_edges.all()):
        raise InputError("bspline_surface: the T-mesh is not a tensor product (it has T-junctions)")
    s_n, t_n = mesh.shape
    m_s = s_n if mesh.periodic else s_n - 4
    m_t = t_n - 4
    grid = ts.control_points.reshape(m_t, m_s, 3).transpose(1, 0, 2)
    w = ts.weights.reshape(m_t, m_s).T
    t_knots = mesh.t_lines[3 : t_n - 3]
    v_mults = [4] + [1] * (len(t_knots) - 2) + [4]
    if mesh.periodic:
        # OCCT's periodic pole k (0-based) is the function on knots u_(k-3) .. u_(k+1)
        # (indices modulo S); bonecad's anchor i has knots i-2 .. i+2: pole k = anchor k-1.
        grid = np.roll(grid, 1, axis=0)
        w = np.roll(w, 1, axis=0)
        u_knots = list(mesh.s_lines) + [mesh.s_lines[0] + mesh.s_period]
        u_mults = [1] * len(u_knots)
    else:
        u_knots = list(mesh.s_lines[3 : s_n - 3])
        u_mults = [4] + [1] * (len(u_knots) - 2) + [4]
    try:
        return Geom_BSplineSurface(
            _poles(grid),
            _weights(w),
            _array1([float(k) for k in u_knots], TColStd_Array1OfReal),
            _array1([float(k) for k in t_knots], TColStd_Array1OfReal),
            _array1(u_mults, TColStd_Array1OfInteger),
            _array1(v_mults, TColStd_Array1OfInteger),
            3,
            3,
            mesh.periodic,
            False,
        )
    except Exception as exc:  # OCP raises Standard_ConstructionError subclasses
        raise KernelError(f"OpenCascade rejected the B-spline surface: {exc}") from exc
