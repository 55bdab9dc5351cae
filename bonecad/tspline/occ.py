"""T-splines to OpenCascade: the only module of bonecad.tspline that imports OCP.

- every Bezier element -> a Geom_BezierSurface (rational when the weights
  differ) -> a face; neighbours' boundary curves are computed from the same
  blending functions, so they agree up to rounding and sewing
  (BRepBuilderAPI_Sewing) joins them, cutting the long edges at T-junctions;
- a tensor-product T-spline -> one Geom_BSplineSurface (periodic in u when s is);
- lean output (``merged_faces``): the elements are partitioned greedily into
  tensor-product blocks (rectangles of whole elements whose interior element
  boundaries run right across; none closes round the periodic s), and each
  block becomes one Geom_BSplineSurface: the Bezier patches joined with triple
  knots, then every interior knot lowered to multiplicity 1 by OpenCascade's
  knot removal (tolerance 1e-7 mm; the T-spline is C2 inside a block).
"""
from __future__ import annotations

import numpy as np
from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace
from OCP.Geom import Geom_BezierSurface, Geom_BSplineSurface
from OCP.gp import gp_Pnt
from OCP.TColgp import TColgp_Array2OfPnt
from OCP.TColStd import TColStd_Array1OfInteger, TColStd_Array1OfReal, TColStd_Array2OfReal
from OCP.TopoDS import TopoDS_Face, TopoDS_Shape

from bonecad.errors import InputError, KernelError
from bonecad.io.brep import sew
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


def to_shell(ts: TSpline, *, tolerance_mm: float = 1e-6) -> TopoDS_Shape:
    """The T-spline as one sewn shell of Bezier faces (open where the T-spline has boundaries)."""
    return sew(bezier_faces(ts, tolerance_mm=0.1 * tolerance_mm), tolerance_mm=tolerance_mm, closed=False)[0]


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


# ------------------------------------------------------------ merged faces
def tensor_product_blocks(ts: TSpline) -> list[np.ndarray]:
    """Partition of the Bezier elements into tensor-product blocks (greedy, maximal rectangles).

    A block is a rectangle of whole elements in index space whose interior
    element boundaries all run across the block, so its elements form a
    grid. Each block is returned as an (n_u, n_v) int array of element
    indices, u along s (increasing), v along t. A block never closes round
    the periodic s direction (it spans fewer cells than the period), so each
    block is an open patch; it may cross s = 0 (its s parameter is unwrapped).
    """
    ext = ts.extraction
    cells = ext.cell_element
    ns, nt = cells.shape
    periodic = ts.mesh.periodic
    ib = ext.index_bounds
    width = ib[:, 1] - ib[:, 0]
    height = ib[:, 3] - ib[:, 2]
    assigned = np.zeros(ext.n_elements, dtype=bool)

    def unwrapped_i0(elems: np.ndarray, col: int) -> np.ndarray:
        """First s-line (unwrapped) of each element, placed so that it covers column ``col``."""
        return col - np.mod(col - ib[elems, 0], ns) if periodic else ib[elems, 0]

    def grid(a: int, b: int, c: int, d: int) -> np.ndarray | None:
        """The block's element grid, or None when the rectangle is no free tensor-product block."""
        if b - a >= ns if periodic else (a < 0 or b > ns):
            return None
        if c < 0 or d > nt:
            return None
        sub = cells[np.arange(a, b) % ns][:, c:d]
        if (sub < 0).any():
            return None
        elems, first, counts = np.unique(sub, return_index=True, return_counts=True)
        if assigned[elems].any() or np.any(counts != width[elems] * height[elems]):
            return None  # an element sticks out of the rectangle, or is taken
        s0 = a + first // (d - c)
        s0 = unwrapped_i0(elems, s0)
        s1 = s0 + width[elems]
        t0, t1 = ib[elems, 2], ib[elems, 3]
        s_breaks = np.unique(np.concatenate([s0, s1]))
        t_breaks = np.unique(np.concatenate([t0, t1]))
        if np.any(np.searchsorted(s_breaks, s0, side="right") != np.searchsorted(s_breaks, s1, side="left")):
            return None
        if np.any(np.searchsorted(t_breaks, t0, side="right") != np.searchsorted(t_breaks, t1, side="left")):
            return None
        out = np.full((len(s_breaks) - 1, len(t_breaks) - 1), -1, dtype=np.int64)
        out[np.searchsorted(s_breaks, s0), np.searchsorted(t_breaks, t0)] = elems
        return out

    def grow(rect: list[int], direction: int) -> list[int] | None:
        a, b, c, d = rect
        if direction == 0:  # +s
            if not periodic and b >= ns:
                return None
            col = cells[b % ns, c:d]
            if (col < 0).any():
                return None
            new = [a, int((unwrapped_i0(col, b) + width[col]).max()), c, d]
        elif direction == 1:  # +t
            if d >= nt:
                return None
            row = cells[np.arange(a, b) % ns, d]
            if (row < 0).any():
                return None
            new = [a, b, c, int(ib[row, 3].max())]
        elif direction == 2:  # -s
            if not periodic and a <= 0:
                return None
            col = cells[(a - 1) % ns, c:d]
            if (col < 0).any():
                return None
            new = [int(unwrapped_i0(col, a - 1).min()), b, c, d]
        else:  # -t
            if c <= 0:
                return None
            row = cells[np.arange(a, b) % ns, c - 1]
            if (row < 0).any():
                return None
            new = [a, b, int(ib[row, 2].min()), d]
        return new if grid(*new) is not None else None

    blocks = []
    for e in np.lexsort((ib[:, 0], ib[:, 2])):
        if assigned[e]:
            continue
        rect = [int(ib[e, 0]), int(ib[e, 1]), int(ib[e, 2]), int(ib[e, 3])]
        changed = True
        while changed:
            changed = False
            for direction in range(4):  # +s, +t, -s, -t (t first: ~5 % fewer faces, larger files)
                new = grow(rect, direction)
                while new is not None:
                    rect, changed = new, True
                    new = grow(rect, direction)
        g = grid(*rect)
        assigned[g.ravel()] = True
        blocks.append(g)
    return blocks


def _block_surface(ts: TSpline, block: np.ndarray, points: np.ndarray, weights: np.ndarray,
                   tolerance_mm: float) -> Geom_BSplineSurface:
    """One block of Bezier patches as one bicubic B-spline surface (u = s, v = t).

    The patches are joined with triple interior knots (exactly the same
    surface), then each interior knot is lowered to multiplicity 1 where
    OpenCascade's knot removal changes the surface by less than tolerance_mm
    (everywhere inside a block of a C2 T-spline).
    """
    ext = ts.extraction
    n_u, n_v = block.shape
    u_knots = np.concatenate([ext.s_bounds[block[:, 0], 0], [ext.s_bounds[block[-1, 0], 1]]])
    # unwrap the s knots of a block that crosses s = 0
    if ts.mesh.periodic:
        u_knots = u_knots[0] + np.concatenate([[0.0], np.cumsum(np.diff(ext.s_bounds[block[:, 0]], axis=1)[:, 0])])
    v_knots = np.concatenate([ext.t_bounds[block[0, :], 0], [ext.t_bounds[block[0, -1], 1]]])
    poles = np.empty((3 * n_u + 1, 3 * n_v + 1, 3))
    w = np.empty((3 * n_u + 1, 3 * n_v + 1))
    for p in range(n_u):
        for q in range(n_v):
            e = block[p, q]
            poles[3 * p : 3 * p + 4, 3 * q : 3 * q + 4] = points[e]
            w[3 * p : 3 * p + 4, 3 * q : 3 * q + 4] = weights[e]
    u_mults = [4] + [3] * (n_u - 1) + [4]
    v_mults = [4] + [3] * (n_v - 1) + [4]
    args = (
        _array1([float(k) for k in u_knots], TColStd_Array1OfReal),
        _array1([float(k) for k in v_knots], TColStd_Array1OfReal),
        _array1(u_mults, TColStd_Array1OfInteger),
        _array1(v_mults, TColStd_Array1OfInteger),
        3,
        3,
    )
    if np.ptp(w) <= _POLYNOMIAL_WEIGHTS * w.max():
        surf = Geom_BSplineSurface(_poles(poles), *args)
    else:
        surf = Geom_BSplineSurface(_poles(poles), _weights(w), *args)
    for k in range(2, n_u + 1):
        surf.RemoveUKnot(k, 1, tolerance_mm)
    for k in range(2, n_v + 1):
        surf.RemoveVKnot(k, 1, tolerance_mm)
    return surf


def merged_surfaces(ts: TSpline, *, tolerance_mm: float = 1e-7) -> list[tuple[object, np.ndarray]]:
    """The T-spline as few surfaces: one per tensor-product block of Bezier elements.

    Returns (surface, block) pairs; a one-element block stays a
    Geom_BezierSurface on [0, 1]^2, a larger block is a Geom_BSplineSurface in
    the T-spline's own parameters (u = s, unwrapped from the block's first
    element, v = t). The surfaces equal the Bezier patches to tolerance_mm.
    """
    points, weights = ts.bezier_points
    out = []
    for block in tensor_product_blocks(ts):
        if block.size == 1:
            p, w = points[block[0, 0]], weights[block[0, 0]]
            if np.ptp(w) <= _POLYNOMIAL_WEIGHTS * w.max():
                out.append((Geom_BezierSurface(_poles(p)), block))
            else:
                out.append((Geom_BezierSurface(_poles(p), _weights(w)), block))
        else:
            out.append((_block_surface(ts, block, points, weights, tolerance_mm), block))
    return out


def merged_faces(ts: TSpline, *, tolerance_mm: float = 1e-7) -> list[tuple[TopoDS_Face, np.ndarray]]:
    """One face per tensor-product block of Bezier elements (natural bounds of its surface),
    with the block's element indices."""
    faces = []
    for surf, block in merged_surfaces(ts, tolerance_mm=tolerance_mm):
        maker = BRepBuilderAPI_MakeFace(surf, tolerance_mm)
        if not maker.IsDone():
            raise KernelError(f"OpenCascade could not make a face of a block of {block.size} Bezier elements "
                              f"(error {maker.Error()})")
        faces.append((maker.Face(), block))
    return faces
