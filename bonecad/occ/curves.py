"""Contour curves to OpenCascade: the one boundary where numpy B-splines become Geom_BSplineCurve edges."""
from __future__ import annotations

import numpy as np

from bonecad.errors import KernelError
from bonecad.splines.curve import BSplineCurve
from bonecad.splines.knots import multiplicities


def to_geom_curve(curve: BSplineCurve):
    """A Geom_BSplineCurve equal to ``curve`` (periodic curves stay periodic, uniform single knots)."""
    from OCP.Geom import Geom_BSplineCurve
    from OCP.gp import gp_Pnt
    from OCP.TColgp import TColgp_Array1OfPnt
    from OCP.TColStd import TColStd_Array1OfInteger, TColStd_Array1OfReal

    from bonecad.occ.brep import array1

    poles = array1([gp_Pnt(*p) for p in np.asarray(curve.control_points, dtype=np.float64).tolist()],
                   TColgp_Array1OfPnt)
    if curve.periodic:
        values = np.asarray(curve.knots, dtype=np.float64)
        counts = np.ones(len(values), dtype=int)
    else:
        values, counts = multiplicities(curve.knots)
    knots = array1([float(v) for v in values], TColStd_Array1OfReal)
    mults = array1([int(m) for m in counts], TColStd_Array1OfInteger)
    try:
        return Geom_BSplineCurve(poles, knots, mults, curve.degree, curve.periodic)
    except Exception as exc:  # OCP raises Standard_ConstructionError
        raise KernelError(f"OpenCascade rejected a B-spline curve ({curve.count} poles): {exc}") from exc


def to_edge(curve: BSplineCurve, name: str = ""):
    """A TopoDS_Edge of ``curve`` (``name`` only for the error message)."""
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeEdge

    maker = BRepBuilderAPI_MakeEdge(to_geom_curve(curve))
    if not maker.IsDone():
        raise KernelError(f"OpenCascade could not make an edge of curve {name!r}")
    return maker.Edge()
