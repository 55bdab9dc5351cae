"""T-splines to OpenCascade: Bezier-extracted faces, merged into B-spline faces per tensor-product block.

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
  knot removal (tolerance 1e-7 mm; the T-spline is C2 inside a block); its face has the natural
  bounds of the surface, or on request one edge per element side (``merged_faces``);
- leaner still (``panel_faces``): one face per rectangle of a panel plan, each the
  T-spline's exact B-spline form over it (knots only where elements break).
"""
from __future__ import annotations

import numpy as np
from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeEdge, BRepBuilderAPI_MakeFace, BRepBuilderAPI_MakeWire
from OCP.BRepLib import BRepLib
from OCP.Geom import Geom_BezierSurface, Geom_BSplineSurface
from OCP.Geom2d import Geom2d_Line
from OCP.gp import gp_Dir2d, gp_Pnt2d
from OCP.TColStd import TColStd_Array1OfInteger, TColStd_Array1OfReal
from OCP.TopoDS import TopoDS_Face, TopoDS_Shape, TopoDS_Wire

from bonecad.errors import KernelError
from bonecad.occ.brep import array1, pole_grid, real_grid, sew
from bonecad.occ.surfaces import to_geom_surface
from bonecad.splines.tspline.tensor import region_patch
from bonecad.splines.tspline.tspline import TSpline

#: Largest relative weight spread still written as a polynomial Bezier patch.
_POLYNOMIAL_WEIGHTS = 1e-14


def bezier_surfaces(ts: TSpline) -> list[Geom_BezierSurface]:
    """One bicubic (rational) Bezier surface per element, u along s, v along t.

    Each patch is parametrised on [0, 1]^2 (the element's local coordinates).
    """
    points, weights = ts.bezier_points
    out = []
    for p, w in zip(points, weights):
        if np.ptp(w) <= _POLYNOMIAL_WEIGHTS * w.max():
            out.append(Geom_BezierSurface(pole_grid(p)))
        else:
            out.append(Geom_BezierSurface(pole_grid(p), real_grid(w)))
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

    Raises ValueError when the T-mesh has T-junctions (not a tensor product).
    """
    mesh = ts.mesh
    if not (mesh.s_edges.all() and mesh.t_edges.all()):
        raise ValueError("bspline_surface: the T-mesh is not a tensor product (it has T-junctions)")
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
            pole_grid(grid),
            real_grid(w),
            array1([float(k) for k in u_knots], TColStd_Array1OfReal),
            array1([float(k) for k in t_knots], TColStd_Array1OfReal),
            array1(u_mults, TColStd_Array1OfInteger),
            array1(v_mults, TColStd_Array1OfInteger),
            3,
            3,
            mesh.periodic,
            False,
        )
    except Exception as exc:  # OCP raises Standard_ConstructionError subclasses
        raise KernelError(f"OpenCascade rejected the B-spline surface: {exc}") from exc


def bspline_face(ts: TSpline, *, tolerance_mm: float = 1e-7) -> TopoDS_Face:
    """A tensor-product T-spline as one face on its whole B-spline surface (:func:`bspline_surface`)."""
    maker = BRepBuilderAPI_MakeFace(bspline_surface(ts), tolerance_mm)
    if not maker.IsDone():
        raise KernelError(f"OpenCascade could not make a face of {ts.n_control} poles (error {maker.Error()})")
    return maker.Face()


# ------------------------------------------------------------ merged faces
def tensor_product_blocks(ts: TSpline) -> list[np.ndarray]:
    """Partition of the Bezier elements into tensor-product blocks (greedy, maximal rectangles).

    A block is a rectangle of whole elements in index space whose interior
    element boundaries all run across the block, so its elements form a
    grid. Each block is returned as an (n_u, n_v) int array of element
    indices, u along s (increasing), v along t. A block never closes round
    the periodic s direction (it spans fewer cells than the period), so each
    block is an open patch; it may cross s = 0 (its s parameter is unwrapped).

    Each block starts as the first free element in (t, s) order and grows by
    one column or row of elements at a time (+s, +t, -s, -t, over and over
    until none fits): free elements of one width (height) whose t (s) bounds
    are exactly the block's grid lines, which is what keeps the grown
    rectangle a free tensor-product block.
    """
    ext = ts.extraction
    ns, nt = ext.cell_element.shape
    periodic = ts.mesh.periodic
    cells = ext.cell_element.tolist()
    i0, i1, j0, j1 = ext.index_bounds.T.tolist()
    assigned = [False] * ext.n_elements

    def fits(e: int, s_lo: int, s_hi: int, t_lo: int, t_hi: int) -> bool:
        """Element e is free and spans exactly s-lines s_lo..s_hi (unwrapped) and t-lines t_lo..t_hi."""
        return (e >= 0 and not assigned[e] and (s_lo - i0[e]) % ns == 0 and i1[e] - i0[e] == s_hi - s_lo
                and j0[e] == t_lo and j1[e] == t_hi)

    def grow(s_lines: list[int], t_lines: list[int], direction: int) -> bool:
        """Add one column (+s, -s) or row (+t, -t) of elements to the block's grid lines, in place.

        Returns False, leaving the lines alone, when no column or row fits.
        """
        a, b, c, d = s_lines[0], s_lines[-1], t_lines[0], t_lines[-1]
        if direction in (0, 2):  # a column right of s-line b (+s) or left of s-line a (-s)
            if not periodic and (b >= ns if direction == 0 else a <= 0):
                return False
            column = cells[b % ns if direction == 0 else (a - 1) % ns]
            first = column[c]
            if first < 0:
                return False
            width = i1[first] - i0[first]
            if periodic and b - a + width >= ns:  # the block would close round s
                return False
            lo, hi = (b, b + width) if direction == 0 else (a - width, a)
            if not all(fits(column[t], lo, hi, t, t_next) for t, t_next in zip(t_lines, t_lines[1:])):
                return False
            if direction == 0:
                s_lines.append(hi)
            else:
                s_lines.insert(0, lo)
        else:  # a row above t-line d (+t) or below t-line c (-t)
            if d >= nt if direction == 1 else c <= 0:
                return False
            row = d if direction == 1 else c - 1
            first = cells[a % ns][row]
            if first < 0:
                return False
            height = j1[first] - j0[first]
            lo, hi = (d, d + height) if direction == 1 else (c - height, c)
            if not all(fits(cells[s % ns][row], s, s_next, lo, hi) for s, s_next in zip(s_lines, s_lines[1:])):
                return False
            if direction == 1:
                t_lines.append(hi)
            else:
                t_lines.insert(0, lo)
        return True

    blocks = []
    for e in np.lexsort((ext.index_bounds[:, 0], ext.index_bounds[:, 2])).tolist():
        if assigned[e]:
            continue
        s_lines, t_lines = [i0[e], i1[e]], [j0[e], j1[e]]
        changed = True
        while changed:
            changed = False
            for direction in range(4):  # +s, +t, -s, -t (t first: ~5 % fewer faces, larger files)
                while grow(s_lines, t_lines, direction):
                    changed = True
        block = [[cells[s % ns][t] for t in t_lines[:-1]] for s in s_lines[:-1]]
        for column in block:
            for element in column:
                assigned[element] = True
        blocks.append(np.array(block, dtype=np.int64))
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
        array1([float(k) for k in u_knots], TColStd_Array1OfReal),
        array1([float(k) for k in v_knots], TColStd_Array1OfReal),
        array1(u_mults, TColStd_Array1OfInteger),
        array1(v_mults, TColStd_Array1OfInteger),
        3,
        3,
    )
    if np.ptp(w) <= _POLYNOMIAL_WEIGHTS * w.max():
        surf = Geom_BSplineSurface(pole_grid(poles), *args)
    else:
        surf = Geom_BSplineSurface(pole_grid(poles), real_grid(w), *args)
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
                out.append((Geom_BezierSurface(pole_grid(p)), block))
            else:
                out.append((Geom_BezierSurface(pole_grid(p), real_grid(w)), block))
        else:
            out.append((_block_surface(ts, block, points, weights, tolerance_mm), block))
    return out


def merged_faces(ts: TSpline, *, tolerance_mm: float = 1e-7,
                 edge_per_element: bool = False) -> list[tuple[TopoDS_Face, np.ndarray]]:
    """One face per tensor-product block of Bezier elements (natural bounds of its surface),
    with the block's element indices.

    edge_per_element : bound each block's face by one edge per element side (a vertex at every
    knot of its sides) instead of one edge per side: the same faces, more edges, sewing 3-5x
    slower. Sewing pairs edges by sampling them (8 points); on a crumpled surface of tiny
    elements (control points moved about as far as the elements are long) a side several
    elements long can curl back to within the sewing tolerance of itself, and sewing left such
    a pair of sides unsewn; one cubic span at a time it sews. The blocks' surfaces must not
    degenerate on a side (the tube's do not; the caps' do at the pole).
    """
    faces = []
    for surf, block in merged_surfaces(ts, tolerance_mm=tolerance_mm):
        if edge_per_element and block.size > 1:
            maker = BRepBuilderAPI_MakeFace(surf, _element_edges_wire(surf, tolerance_mm), True)
        else:
            maker = BRepBuilderAPI_MakeFace(surf, tolerance_mm)
        if not maker.IsDone():
            raise KernelError(f"OpenCascade could not make a face of a block of {block.size} Bezier elements "
                              f"(error {maker.Error()})")
        faces.append((maker.Face(), block))
    return faces


def panel_faces(ts: TSpline, panels, *, tolerance_mm: float = 1e-7,
                edge_per_span: bool = False) -> list[TopoDS_Face]:
    """One face per rectangle (s0, s1, t0, t1) of ``panels``: the T-spline's exact clamped B-spline
    form over it (:func:`~bonecad.splines.tspline.tensor.region_patch`), bounded naturally or, with
    ``edge_per_span``, by one edge per knot span of its sides (see ``merged_faces``)."""
    faces = []
    for s0, s1, t0, t1 in panels:
        surf = to_geom_surface(region_patch(ts, (s0, s1), (t0, t1)))
        maker = (BRepBuilderAPI_MakeFace(surf, _element_edges_wire(surf, tolerance_mm), True) if edge_per_span
                 else BRepBuilderAPI_MakeFace(surf, tolerance_mm))
        if not maker.IsDone():
            raise KernelError(f"OpenCascade could not make the face of the panel s {s0:.2f}-{s1:.2f}, "
                              f"t {t0:.2f}-{t1:.2f} (error {maker.Error()})")
        faces.append(maker.Face())
    return faces


def _element_edges_wire(surf: Geom_BSplineSurface, tolerance_mm: float) -> TopoDS_Wire:
    """The boundary of ``surf``'s parameter rectangle, counterclockwise, one edge per knot span:
    isoparametric lines on the surface (the 3D curves are the surface's own isolines)."""
    u0, u1, v0, v1 = surf.Bounds()
    u_knots = [surf.UKnot(k) for k in range(1, surf.NbUKnots() + 1)]
    v_knots = [surf.VKnot(k) for k in range(1, surf.NbVKnots() + 1)]
    wire = BRepBuilderAPI_MakeWire()
    sides = (((u0, v0), (1.0, 0.0), u_knots), ((u1, v0), (0.0, 1.0), v_knots),
             ((u1, v1), (-1.0, 0.0), u_knots[::-1]), ((u0, v1), (0.0, -1.0), v_knots[::-1]))
    for start, direction, knots in sides:
        line = Geom2d_Line(gp_Pnt2d(*start), gp_Dir2d(*direction))
        for a, b in zip(knots[:-1], knots[1:]):
            edge = BRepBuilderAPI_MakeEdge(line, surf, abs(a - knots[0]), abs(b - knots[0])).Edge()
            if not BRepLib.BuildCurve3d_s(edge, tolerance_mm):
                raise KernelError("OpenCascade could not make the 3D curve of a B-spline face's edge")
            wire.Add(edge)
    if not wire.IsDone():
        raise KernelError(f"OpenCascade could not make the boundary of a B-spline face (error {wire.Error()})")
    return wire.Wire()
