"""Fine tessellation of an OpenCascade shape, checked against the exact face areas.

This is the one place where the analysis reads OpenCascade geometry into numpy:
triangle nodes, their (u, v) on each face, and each face's surface as a
:class:`~bonecad.splines.evaluate.SplineSurface` for exact refinement.

Pitfall handled (DESIGN.md): ``BRepMesh_IncrementalMesh`` can cover only part of
a large periodic B-spline face. Every face's triangulated area is compared with
its exact area from ``BRepGProp.SurfaceProperties_s`` with an explicit relative
tolerance (adaptive Gauss integration); a face short by more than
``coverage_tolerance`` raises :class:`~bonecad.errors.KernelError`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from bonecad.errors import InputError, KernelError
from bonecad.mesh.sampling import triangle_areas
from bonecad.occ.brep import edges, nonempty_faces, read_array1, wires
from bonecad.mesh.closest import vertex_normals
from bonecad.splines.evaluate import SplineSurface, SurfaceSet, project, project_faces


def _setting(key: str):
    from bonecad.config import load_config

    return lambda: float(load_config()["analysis"][key])


@dataclass(frozen=True)
class TessellationSettings:
    """Tolerances of the tessellation (mm, rad); defaults from ``[analysis]`` in defaults.toml.

    deflection_mm : chord error aimed at (``tessellation_deflection_mm``). It
        bounds distances that are not refined on the exact surface (a tiny share
        of the samples; the colour map's vertex distances) and sets how close the
        Newton start is; the chord error is measured and reported, never assumed.
    angular_deflection_rad : largest turn of a surface normal along one edge.
    coverage_tolerance : relative area shortfall accepted per face. A chordal
        tessellation is short by about deflection/radius (1e-3 for 0.02 mm on a
        20 mm radius); 0.5 % leaves margin for that and still catches the
        known partial-coverage failure (20 % missing). A face only a few
        millimetres across is curved on its own scale, so it may fall short by
        up to ``small_face_factor`` x deflection / sqrt(area) (see :meth:`allowed_shortfall`).
    area_rel_eps : relative error asked of BRepGProp's adaptive integration
        (default settings were 1 % off on large B-spline faces).
    max_edge_mm : longest triangle edge (per parameter direction on grid faces;
        longer BRepMesh edges are bisected). The closest-point search assumes
        compact triangles.
    """

    deflection_mm: float = field(default_factory=_setting("tessellation_deflection_mm"))
    angular_deflection_rad: float = field(default_factory=_setting("tessellation_angular_deflection_rad"))
    coverage_tolerance: float = field(default_factory=_setting("coverage_tolerance"))
    area_rel_eps: float = field(default_factory=_setting("area_rel_eps"))
    max_edge_mm: float = field(default_factory=_setting("tessellation_max_edge_mm"))
    small_face_factor: float = field(default_factory=_setting("small_face_shortfall_factor"))

    def allowed_shortfall(self, exact_area_mm2: np.ndarray) -> np.ndarray:
        """Relative area shortfall accepted for faces of these exact areas: the coverage
        tolerance, or the chordal shortfall of a face curved on its own size (a 1 mm^2
        cap face next to an apex), whichever is larger. A 20 % partial cover is still
        refused on every face above 0.25 mm^2 at 0.05 mm deflection."""
        size = np.sqrt(np.maximum(np.asarray(exact_area_mm2, dtype=np.float64), 1e-300))
        return np.maximum(self.coverage_tolerance, self.small_face_factor * self.deflection_mm / size)


@dataclass(frozen=True)
class Tessellation:
    """Triangles of every face of a shape, with exact-surface data per node.

    vertices : (n, 3) float, mm
    triangles : (m, 3) int, oriented so the right-hand normal points out of the
        material (face orientation applied)
    uv : (n, 2) float, parameters of each node on its face's spline surface
    normals : (n, 3) float, exact unit surface normals at the nodes, oriented like
        the triangles
    node_face, triangle_face : (n,), (m,) int, face index of each node / triangle
    face_area_exact_mm2, face_area_mesh_mm2 : (F,) float
    surfaces : one SplineSurface per face, or None where the face could not be
        converted (distances on it stay tessellation-based)
    reversed_faces : (F,) bool, face orientation is REVERSED (flip S_u x S_v)
    chord_error_mm : (F,) float, measured largest distance between triangles
        (centroids, edge midpoints, circumcentres) and the exact surface; computed
        when first asked for (``chord_error_near`` measures only some triangles)
    """

    vertices: np.ndarray
    triangles: np.ndarray
    uv: np.ndarray
    normals: np.ndarray
    node_face: np.ndarray
    triangle_face: np.ndarray
    face_area_exact_mm2: np.ndarray
    face_area_mesh_mm2: np.ndarray
    surfaces: tuple[SplineSurface | None, ...]
    reversed_faces: np.ndarray
    faces: tuple  # TopoDS_Face, in the order of the face index
    surface_set: SurfaceSet | None = None  # the surfaces packed for batched evaluation
    native_faces: np.ndarray | None = None  # (F,) bool, the face lies on its spline surface with the same (u, v)

    def __post_init__(self) -> None:
        if self.surface_set is None:
            object.__setattr__(self, "surface_set", SurfaceSet(self.surfaces))
        if self.native_faces is None:
            object.__setattr__(self, "native_faces", np.zeros(len(self.surfaces), dtype=bool))

    @property
    def face_count(self) -> int:
        return len(self.faces)

    @cached_property
    def chord_error_mm(self) -> np.ndarray:
        return chord_errors(self.surface_set, self.vertices, self.uv, self.triangles, self.triangle_face,
                            self.face_count)

    def chord_error_near(self, points: np.ndarray, distance_mm: np.ndarray) -> float:
        """Largest chord error (mm) of the triangles within reach of query points (0.0 for none).

        A point's distance measured on the tessellation (``distance_mm``) differs
        from its exact distance by at most the chord error of the triangles that
        come within that distance of it, plus one triangle; so only triangles whose
        centroid lies within distance + the longest triangle edge are measured.
        """
        from scipy.spatial import cKDTree

        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(points) == 0:
            return 0.0
        t = self.vertices[self.triangles]
        edge = max(float(np.linalg.norm(t[:, (k + 1) % 3] - t[:, k], axis=1).max()) for k in range(3))
        reach = np.abs(np.asarray(distance_mm, dtype=np.float64)) + edge
        hits = cKDTree(t.mean(axis=1)).query_ball_point(points, reach, workers=-1)
        near = np.unique(np.concatenate([np.asarray(h, dtype=np.int64) for h in hits]))
        if len(near) == 0:
            return 0.0
        chord = chord_errors(self.surface_set, self.vertices, self.uv, self.triangles[near],
                             self.triangle_face[near], self.face_count)
        return float(chord.max())

    def triangle_areas(self) -> np.ndarray:
        return triangle_areas(self.vertices, self.triangles)


def exact_face_area(face, rel_eps: float = 1e-6) -> float:
    """Area of one face (mm^2) by adaptive Gauss integration to relative error ``rel_eps``."""
    from OCP.BRepGProp import BRepGProp
    from OCP.GProp import GProp_GProps

    props = GProp_GProps()
    BRepGProp.SurfaceProperties_s(face, props, rel_eps)
    return float(props.Mass())


def face_spline_surface(face) -> tuple[SplineSurface | None, bool]:
    """The face's surface as a clamped SplineSurface over the face's parameter range.

    Returns ``(surface, native)``: ``native`` is True when the face already lies on a
    Geom_BSplineSurface/Geom_BezierSurface (same parameterisation as the face), False
    when it was converted (plane, cylinder, sphere...: parameters differ from the
    face's, exact geometry). ``surface`` is None when conversion failed.
    """
    from OCP.BRep import BRep_Tool
    from OCP.BRepTools import BRepTools
    from OCP.Geom import Geom_BezierSurface, Geom_BSplineSurface, Geom_RectangularTrimmedSurface
    from OCP.GeomConvert import GeomConvert
    from OCP.Standard import Standard_Failure

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
    poles = np.empty((nu, nv, 4))
    rational = bs.IsURational() or bs.IsVRational()
    for i in range(1, nu + 1):
        for j in range(1, nv + 1):
            p = bs.Pole(i, j)
            w = bs.Weight(i, j) if rational else 1.0
            poles[i - 1, j - 1] = (w * p.X(), w * p.Y(), w * p.Z(), w)
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
        closed.append(bool(periodic and abs((hi - lo) - period()) <= 1e-9 * max(1.0, period())))
    return (
        SplineSurface(
            bs.UDegree(), bs.VDegree(), knots_u, knots_v, poles, bounds, closed[0], closed[1]
        ),
        native,
    )


def _native_to_spline_uv(face, surface: SplineSurface, uv: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """Parameters on a converted surface for nodes given in the face's own parameters.

    The conversion keeps the parameter ranges but not the parameterisation (rational
    arcs), so the native parameters, rescaled to the spline range, are only a
    start: Gauss-Newton on the node positions gives the exact ones.
    """
    from OCP.BRepTools import BRepTools

    u0, u1, v0, v1 = BRepTools.UVBounds_s(face)
    b = surface.bounds
    start = np.column_stack(
        [
            b[0] + (uv[:, 0] - u0) / max(u1 - u0, 1e-300) * (b[1] - b[0]),
            b[2] + (uv[:, 1] - v0) / max(v1 - v0, 1e-300) * (b[3] - b[2]),
        ]
    )
    return project(surface, nodes, start).uv


def is_natural(face, surface: SplineSurface) -> bool:
    """True when ``face`` is its surface's whole parameter rectangle ``surface.bounds``.

    Rigorous test on the boundary: one wire, and every edge's p-curve is a
    straight line lying on a side of the rectangle (iso-lines; degenerate edges
    at poles included). Such a face is tessellated on a parameter grid, which
    covers it completely by construction.
    """
    from OCP.BRepAdaptor import BRepAdaptor_Curve2d
    from OCP.BRepTools import BRepTools
    from OCP.GeomAbs import GeomAbs_Line

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


def _breaks(knots: np.ndarray, lo: float, hi: float) -> np.ndarray:
    inner = np.unique(knots[(knots > lo) & (knots < hi)])
    return np.concatenate([[lo], inner, [hi]])


#: samples per knot span and cross lines per face used to size a grid
_SIZE_SAMPLES, _SIZE_LINES = 5, 5


def _grid_counts(sset: SurfaceSet, faces: list[int], breaks: list[tuple[np.ndarray, np.ndarray]], settings, factor):
    """Segments per knot span, per face and direction, from sampled iso-lines.

    A span is split into n segments so that (a) no segment is longer than
    ``max_edge_mm``, (b) the sag of a chord, |C''| (span / n)^2 / 8 with C''
    from second differences, stays below ``deflection_mm``, and (c) the
    iso-line turns by at most ``angular_deflection_rad`` per segment.
    """
    m = _SIZE_SAMPLES
    t = np.linspace(0.0, 1.0, m)
    c = np.linspace(0.0, 1.0, _SIZE_LINES)
    factor = np.asarray(factor, dtype=np.float64)
    faces_arr = np.asarray(faces, dtype=np.int64)
    out: list[list] = [[None] * len(faces), [None] * len(faces)]
    # faces with as many knot spans each way are sized together
    by_spans: dict[tuple[int, int], list[int]] = {}
    for i, (bu, bv) in enumerate(breaks):
        by_spans.setdefault((len(bu), len(bv)), []).append(i)
    for members in by_spans.values():
        fids = faces_arr[members]
        all_u = np.array([breaks[i][0] for i in members])
        all_v = np.array([breaks[i][1] for i in members])
        for direction in (0, 1):
            along, across = (all_u, all_v) if direction == 0 else (all_v, all_u)
            lo, hi = along[:, :-1], along[:, 1:]  # (F, S)
            par = lo[..., None] + (hi - lo)[..., None] * t  # (F, S, m)
            # cross lines: evenly spaced, mid-span and at the knots (a repeated line changes no maximum)
            cross = np.concatenate(
                [across[:, :1] + (across[:, -1:] - across[:, :1]) * c, 0.5 * (across[:, :-1] + across[:, 1:]), across],
                axis=1,
            )  # (F, K)
            count, spans = lo.shape
            shape = (count, spans, cross.shape[1], m)
            grid_a = np.broadcast_to(par[:, :, None, :], shape)
            grid_c = np.broadcast_to(cross[:, None, :, None], shape)
            uu, vv = (grid_a, grid_c) if direction == 0 else (grid_c, grid_a)
            fid = np.broadcast_to(fids[:, None, None, None], shape)
            pts = sset.evaluate(fid.ravel(), uu.ravel(), vv.ravel())[0].reshape(*shape, 3)
            d = np.diff(pts, axis=3)
            size = np.linalg.norm(d, axis=4)
            dn = d / np.maximum(size[..., None], 1e-300)
            turn = np.arccos(np.clip(np.einsum("fskmj,fskmj->fskm", dn[..., 1:, :], dn[..., :-1, :]), -1, 1))
            length = size.sum(axis=3).max(axis=2)  # (F, S): longest sampled iso-line per span
            second = np.linalg.norm(pts[..., 2:, :] - 2 * pts[..., 1:-1, :] + pts[..., :-2, :], axis=4).max(axis=(2, 3))
            turns = (turn.sum(axis=3) * (m - 1) / max(m - 2, 1)).max(axis=2)
            n = np.maximum.reduce(
                [
                    np.ones_like(length),
                    np.ceil(length / settings.max_edge_mm),
                    np.ceil((m - 1) * np.sqrt(second / (8.0 * settings.deflection_mm))),
                    np.ceil(turns / settings.angular_deflection_rad),
                ]
            )
            n = np.minimum(n * factor[members][:, None], 1000).astype(np.int64)
            for row, i in enumerate(members):
                out[direction][i] = n[row]
    return out


def _subdivide(breaks: np.ndarray, counts: np.ndarray) -> np.ndarray:
    parts = [np.linspace(a, b, n, endpoint=False) for a, b, n in zip(breaks[:-1], breaks[1:], counts)]
    return np.concatenate(parts + [breaks[-1:]])


def _grid_tessellation(sset: SurfaceSet, faces: list[int], reversed_faces: np.ndarray, settings, factor):
    """Parameter-grid triangles of untrimmed spline faces, all faces in one batch.

    Returns nodes, uv, triangles (local to this batch), node_face, triangle_face,
    exact area per face (2x2 Gauss-Legendre per grid cell of |S_u x S_v|).
    """
    breaks = []
    for f in faces:
        s = sset.surfaces[f]
        u0, u1, v0, v1 = s.bounds
        breaks.append((_breaks(s.knots_u, u0, u1), _breaks(s.knots_v, v0, v1)))
    counts_u, counts_v = _grid_counts(sset, faces, breaks, settings, factor)
    grids = [(_subdivide(bu, cu), _subdivide(bv, cv)) for (bu, bv), cu, cv in zip(breaks, counts_u, counts_v)]
    # faces with the same grid size share one index pattern: build them together
    by_size: dict[tuple[int, int], list[int]] = {}
    for i, (gu, gv) in enumerate(grids):
        by_size.setdefault((len(gu), len(gv)), []).append(i)
    faces_arr = np.asarray(faces, dtype=np.int64)
    uvs, tris, node_face, tri_face, quads, quad_face = [], [], [], [], [], []
    offset = 0
    for (nu, nv), members in by_size.items():
        count = len(members)
        fids = faces_arr[members]
        gu = np.array([grids[i][0] for i in members])  # (F, nu)
        gv = np.array([grids[i][1] for i in members])  # (F, nv)
        uu = np.broadcast_to(gu[:, :, None], (count, nu, nv))
        vv = np.broadcast_to(gv[:, None, :], (count, nu, nv))
        uvs.append(np.column_stack([uu.ravel(), vv.ravel()]))
        idx = np.arange(nu * nv).reshape(nu, nv)
        a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
        pattern = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
        tri = pattern[None] + (offset + nu * nv * np.arange(count))[:, None, None]  # (F, T, 3)
        flip = reversed_faces[fids]
        tri[flip] = tri[flip][:, :, [0, 2, 1]]
        tris.append(tri.reshape(-1, 3))
        node_face.append(np.repeat(fids, nu * nv))
        tri_face.append(np.repeat(fids, len(pattern)))
        cells = (nu - 1) * (nv - 1)
        q0u = np.broadcast_to(gu[:, :-1, None], (count, nu - 1, nv - 1)).ravel()
        q1u = np.broadcast_to(gu[:, 1:, None], (count, nu - 1, nv - 1)).ravel()
        q0v = np.broadcast_to(gv[:, None, :-1], (count, nu - 1, nv - 1)).ravel()
        q1v = np.broadcast_to(gv[:, None, 1:], (count, nu - 1, nv - 1)).ravel()
        quads.append(np.column_stack([q0u, q1u, q0v, q1v]))
        quad_face.append(np.repeat(fids, cells))
        offset += count * nu * nv
    uv = np.concatenate(uvs)
    node_face = np.concatenate(node_face)
    triangles = np.concatenate(tris)
    quads = np.concatenate(quads)
    quad_face = np.concatenate(quad_face)
    triangle_face = np.concatenate(tri_face)
    # exact area: 2x2 Gauss-Legendre on every grid cell
    g = 0.5 / np.sqrt(3.0)
    mid_u, half_u = 0.5 * (quads[:, 0] + quads[:, 1]), quads[:, 1] - quads[:, 0]
    mid_v, half_v = 0.5 * (quads[:, 2] + quads[:, 3]), quads[:, 3] - quads[:, 2]
    gu = np.concatenate([mid_u - g * half_u, mid_u + g * half_u, mid_u - g * half_u, mid_u + g * half_u])
    gv = np.concatenate([mid_v - g * half_v, mid_v - g * half_v, mid_v + g * half_v, mid_v + g * half_v])
    _, su, sv = sset.evaluate(np.tile(quad_face, 4), gu, gv)
    jac = np.linalg.norm(np.cross(su, sv), axis=1) * np.tile(0.25 * half_u * half_v, 4)
    area = np.bincount(np.tile(quad_face, 4), weights=jac, minlength=len(sset.surfaces))
    return uv, triangles, node_face, triangle_face, area


def _refined_grid(sset: SurfaceSet, grid_faces: list[int], reversed_faces: np.ndarray, settings, count: int):
    """Grid tessellation of ``grid_faces``; a face short of its exact area by more than the
    coverage tolerance (a chordal shortfall on a small, tightly curved face) is gridded
    again, twice as fine, up to three times; only those faces are redone.

    Returns uv, triangles, node_face, triangle_face (as :func:`_grid_tessellation`),
    exact area (count,) and the evaluation (S, S_u, S_v) at the nodes.
    """
    batches = []
    todo = np.asarray(grid_faces, dtype=np.int64)
    factor = np.ones(count)
    area = np.zeros(count)
    for attempt in range(4):
        uv, tri, nf, tf, batch_area = _grid_tessellation(sset, todo.tolist(), reversed_faces, settings, factor[todo])
        s, su, sv = sset.evaluate(nf, uv[:, 0], uv[:, 1])
        batches.append((uv, tri, nf, tf, s, su, sv))
        area[todo] = batch_area[todo]
        mesh = np.bincount(tf, weights=triangle_areas(s, tri), minlength=count)[todo]
        exact = area[todo]
        short = (exact > 0) & ((exact - mesh) / np.where(exact > 0, exact, 1.0) > settings.allowed_shortfall(exact))
        if not short.any() or attempt == 3:
            break
        todo = todo[short]
        factor[todo] *= 2
    # each face keeps its last gridding
    last = np.full(count, -1)
    for b, batch in enumerate(batches):
        last[np.unique(batch[2])] = b
    parts = [[] for _ in range(7)]
    offset = 0
    for b, (uv, tri, nf, tf, s, su, sv) in enumerate(batches):
        keep_node = last[nf] == b
        keep_tri = last[tf] == b
        remap = np.cumsum(keep_node) - 1 + offset
        for part, arr in zip(parts, (uv[keep_node], remap[tri[keep_tri]], nf[keep_node], tf[keep_tri],
                                     s[keep_node], su[keep_node], sv[keep_node])):
            part.append(arr)
        offset += int(keep_node.sum())
    uv, tri, nf, tf, s, su, sv = (np.concatenate(part) for part in parts)
    return uv, tri, nf, tf, area, (s, su, sv)


def tessellate(shape, settings: TessellationSettings | None = None) -> Tessellation:
    """Tessellate ``shape`` (any TopoDS_Shape with faces) and read it into numpy.

    Untrimmed spline faces (B-spline, Bezier: :func:`is_natural`) are
    tessellated on a parameter grid, all in one batch; other faces by BRepMesh,
    read face by face and checked against their exact area. Raises KernelError
    when BRepMesh fails or leaves a face covered short of its exact area by
    more than ``settings.coverage_tolerance``.
    """
    from OCP.TopAbs import TopAbs_REVERSED

    settings = settings or TessellationSettings()
    if settings.deflection_mm <= 0 or settings.max_edge_mm <= 0 or settings.angular_deflection_rad <= 0:
        raise InputError(
            f"deflection_mm, max_edge_mm and angular_deflection_rad must be > 0, got {settings.deflection_mm}, "
            f"{settings.max_edge_mm}, {settings.angular_deflection_rad}"
        )
    faces = nonempty_faces(shape)
    count = len(faces)
    surfaces, natural, natives = [], [], []
    for face in faces:
        surface, native = face_spline_surface(face)
        surfaces.append(surface)
        natives.append(native)
        natural.append(surface is not None and native and is_natural(face, surface))
    reversed_arr = np.array([face.Orientation() == TopAbs_REVERSED for face in faces], dtype=bool)
    sset = SurfaceSet(surfaces)
    grid_faces = [i for i in range(count) if natural[i]]
    other_faces = [i for i in range(count) if not natural[i]]
    area_exact = np.zeros(count)
    uv_parts, tri_parts, nf_parts, tf_parts, vert_parts = [], [], [], [], []
    offset = 0
    grid_eval = None
    if grid_faces:
        uv, tri, nf, tf, area, grid_eval = _refined_grid(sset, grid_faces, reversed_arr, settings, count)
        area_exact[grid_faces] = area[grid_faces]
        vert_parts.append(None)  # evaluated with the grid
        uv_parts.append(uv)
        tri_parts.append(tri)
        nf_parts.append(nf)
        tf_parts.append(tf)
        offset = len(uv)
    for index in other_faces:
        nodes, uv, tri, exact = brepmesh_face(
            faces[index], index, surfaces[index], natives[index], reversed_arr[index], settings
        )
        area_exact[index] = exact
        vert_parts.append(nodes)
        uv_parts.append(uv)
        tri_parts.append(tri + offset)
        nf_parts.append(np.full(len(nodes), index))
        tf_parts.append(np.full(len(tri), index))
        offset += len(nodes)
    uv_all = np.concatenate(uv_parts)
    triangles = np.concatenate(tri_parts)
    node_face_all = np.concatenate(nf_parts)
    tri_face_all = np.concatenate(tf_parts)
    vertices = np.zeros((len(uv_all), 3))
    if grid_faces:
        n_grid = len(uv_parts[0])
        vertices[:n_grid] = grid_eval[0]
    if grid_faces:
        # grid rows collapsed to a point (at poles) leave triangles with a zero-length edge: drop them
        grid = np.arange(len(tri_parts[0]))  # the grid triangles come first
        t = vertices[triangles[grid]]
        scale = 1e-12 * max(1.0, float(np.abs(vertices[:n_grid]).max()))
        dead = np.zeros(len(grid), dtype=bool)
        for i, j in ((0, 1), (1, 2), (2, 0)):
            dead |= np.linalg.norm(t[:, i] - t[:, j], axis=1) <= scale
        if dead.any():
            keep = np.ones(len(triangles), dtype=bool)
            keep[grid[dead]] = False
            triangles, tri_face_all = triangles[keep], tri_face_all[keep]
    rest = [v for v in vert_parts if v is not None]
    if rest:
        vertices[offset - sum(len(v) for v in rest) :] = np.concatenate(rest)
    # exact normals at every node with a spline surface
    normals = np.zeros_like(vertices)
    has = np.flatnonzero(sset.group[node_face_all] >= 0)
    if len(has):
        su, sv = np.empty((len(has), 3)), np.empty((len(has), 3))
        n_grid = len(grid_eval[0]) if grid_faces else 0  # grid nodes come first, already evaluated
        in_grid = has < n_grid
        if in_grid.any():
            su[in_grid], sv[in_grid] = grid_eval[1][has[in_grid]], grid_eval[2][has[in_grid]]
        if not in_grid.all():
            rest_nodes = has[~in_grid]
            _, su[~in_grid], sv[~in_grid] = sset.evaluate(
                node_face_all[rest_nodes], uv_all[rest_nodes, 0], uv_all[rest_nodes, 1]
            )
        n = np.cross(su, sv)
        size = np.linalg.norm(n, axis=1, keepdims=True)
        # degenerate points (poles, collapsed rows): no surface normal; left to the mesh below
        good = size[:, 0] > 1e-10 * np.linalg.norm(su, axis=1) * np.linalg.norm(sv, axis=1)
        n = np.where(good[:, None], n / np.maximum(size, 1e-300), 0.0)
        normals[has] = np.where(reversed_arr[node_face_all[has]][:, None], -n, n)
    missing = np.linalg.norm(normals, axis=1) == 0
    if missing.any():
        normals[missing] = vertex_normals(vertices, triangles)[missing]
    tri_area = triangle_areas(vertices, triangles)
    area_mesh = np.bincount(tri_face_all, weights=tri_area, minlength=count)
    short = (area_exact > 0) & (
        (area_exact - area_mesh) / np.where(area_exact > 0, area_exact, 1.0) > settings.allowed_shortfall(area_exact)
    )
    if short.any():
        index = int(np.flatnonzero(short)[0])
        raise KernelError(
            f"face {index}: tessellation covers {area_mesh[index]:.4g} mm^2 of {area_exact[index]:.4g} mm^2 "
            f"({100 * area_mesh[index] / area_exact[index]:.2f} %); refusing a tessellation-based distance"
        )
    return Tessellation(
        vertices=vertices,
        triangles=triangles,
        uv=uv_all,
        normals=normals,
        node_face=node_face_all,
        triangle_face=tri_face_all,
        face_area_exact_mm2=area_exact,
        face_area_mesh_mm2=area_mesh,
        surfaces=tuple(surfaces),
        reversed_faces=reversed_arr,
        faces=tuple(faces),
        surface_set=sset,
        native_faces=np.array(natives, dtype=bool),
    )


def brepmesh_face(face, index: int, surface, native: bool, is_reversed: bool, settings):
    """BRepMesh triangles of one (trimmed or analytic) face: nodes, uv on ``surface``, triangles, exact area."""
    from OCP.BRep import BRep_Tool
    from OCP.BRepMesh import BRepMesh_IncrementalMesh
    from OCP.TopLoc import TopLoc_Location

    mesher = BRepMesh_IncrementalMesh(face, settings.deflection_mm, False, settings.angular_deflection_rad, True)
    if not mesher.IsDone():
        raise KernelError(f"BRepMesh_IncrementalMesh failed on face {index}")
    loc = TopLoc_Location()
    poly = BRep_Tool.Triangulation_s(face, loc)
    if poly is None or poly.NbTriangles() == 0:
        raise KernelError(f"face {index} has no triangulation after BRepMesh")
    trsf = loc.Transformation()
    count = poly.NbNodes()
    nodes = np.empty((count, 3))
    uv = np.empty((count, 2))
    for i in range(count):
        p = poly.Node(i + 1).Transformed(trsf)
        q = poly.UVNode(i + 1)
        nodes[i] = p.X(), p.Y(), p.Z()
        uv[i] = q.X(), q.Y()
    tri = np.array([poly.Triangle(i).Get() for i in range(1, poly.NbTriangles() + 1)], dtype=np.int64) - 1
    if is_reversed:
        tri = tri[:, [0, 2, 1]]
    mesh_area = triangle_areas(nodes, tri).sum()
    exact = exact_face_area(face, settings.area_rel_eps)
    if exact > 0 and (exact - mesh_area) / exact > settings.allowed_shortfall(exact):
        raise KernelError(
            f"face {index}: tessellation covers {mesh_area:.4g} mm^2 of {exact:.4g} mm^2 "
            f"({100 * mesh_area / exact:.2f} %); refusing a tessellation-based distance"
        )
    if surface is not None and not native:
        uv = _native_to_spline_uv(face, surface, uv, nodes)
    nodes, uv, tri = _bisect_long_edges(nodes, uv, tri, surface, settings.max_edge_mm)
    return nodes, uv, tri, exact


def _eval(surface: SplineSurface, uv: np.ndarray):
    from bonecad.splines.evaluate import evaluate

    return evaluate(surface, uv[:, 0], uv[:, 1])


def chord_errors(sset: SurfaceSet, vertices, uv, triangles, triangle_face, face_count: int) -> np.ndarray:
    """(F,) largest distance (mm) from sampled triangle points to the exact surface, per face.

    Sampled on every triangle at the centroid, the edge midpoints and the
    circumcentre (where the chord error of a triangle inscribed in a sphere,
    the osculating surface, peaks; for an obtuse triangle it is the middle of
    the longest edge, sampled already). A measured value by exact projection,
    not BRepMesh's requested deflection (which BRepMesh exceeds by 2x on
    spheres). |p - S(uv)| at the sample's interpolated (u, v) is an upper
    bound of its distance; only samples whose bound exceeds the largest exact
    distance found so far on their face are projected, so the result is the
    exact maximum over all samples at a fraction of the projections. Faces
    without a spline surface get 0 (their triangles are the geometry).
    """
    chord = np.zeros(face_count)
    keep = sset.group[triangle_face] >= 0
    if not keep.any():
        return chord
    triangles, triangle_face = triangles[keep], triangle_face[keep]
    weights = np.array([[1 / 3, 1 / 3, 1 / 3], [0.5, 0.5, 0.0], [0.0, 0.5, 0.5], [0.5, 0.0, 0.5]])
    t = vertices[triangles]
    a2 = np.sum((t[:, 1] - t[:, 2]) ** 2, axis=1)
    b2 = np.sum((t[:, 2] - t[:, 0]) ** 2, axis=1)
    c2 = np.sum((t[:, 0] - t[:, 1]) ** 2, axis=1)
    cc = np.column_stack([a2 * (b2 + c2 - a2), b2 * (c2 + a2 - b2), c2 * (a2 + b2 - c2)])
    total = cc.sum(axis=1, keepdims=True)
    acute = np.all(cc > 0, axis=1)
    cc = np.where(acute[:, None], cc / np.where(total > 0, total, 1.0), 1 / 3)
    bary = np.concatenate([np.broadcast_to(weights, (len(t), 4, 3)), cc[:, None, :]], axis=1)
    pts = np.einsum("mwk,mkj->mwj", bary, t).reshape(-1, 3)
    start = np.einsum("mwk,mkj->mwj", bary, uv[triangles]).reshape(-1, 2)
    face = np.repeat(triangle_face, 5)
    bound = np.linalg.norm(pts - sset.evaluate(face, start[:, 0], start[:, 1])[0], axis=1)

    def exact(sel):
        proj = project_faces(sset, face[sel], pts[sel], start[sel])
        d = np.linalg.norm(pts[sel] - proj.foot, axis=1)
        converged = proj.residual_mm < 1e-6 + 1e-3 * d
        return np.where(converged, d, bound[sel])  # not converged: keep the upper bound

    # first each face's sample of largest bound
    order = np.lexsort((-bound, face))
    first = order[np.r_[True, face[order][1:] != face[order][:-1]]]
    np.maximum.at(chord, face[first], exact(first))
    # then the rest that could beat it, largest bound first, in growing batches: each
    # batch raises the maxima and drops the samples whose bound no longer exceeds them
    todo = np.flatnonzero(bound > chord[face])
    todo = todo[np.argsort(-bound[todo], kind="stable")]
    batch = 4096
    while len(todo):
        head, todo = todo[:batch], todo[batch:]
        np.maximum.at(chord, face[head], exact(head))
        todo = todo[bound[todo] > chord[face[todo]]]
        batch *= 4
    return chord


def _bisect_long_edges(nodes, uv, tri, surface, max_edge_mm: float):
    """Split triangles at the middle (in uv) of their longest edge until no edge exceeds max_edge_mm.

    The new node is placed on the exact surface when there is one. Neighbours are
    not split, so the result need not be conforming; distance queries do not
    need it to be.
    """
    nodes, uv, tri = nodes.copy(), uv.copy(), tri.copy()
    for _ in range(40):
        t = nodes[tri]
        lengths = np.stack([np.linalg.norm(t[:, (k + 1) % 3] - t[:, k], axis=1) for k in range(3)], axis=1)
        longest = np.argmax(lengths, axis=1)
        split = np.flatnonzero(lengths[np.arange(len(tri)), longest] > max_edge_mm)
        if len(split) == 0:
            break
        k = longest[split]
        a = tri[split, k]
        b = tri[split, (k + 1) % 3]
        c = tri[split, (k + 2) % 3]
        mid_uv = 0.5 * (uv[a] + uv[b])
        if surface is not None:
            mid = _eval(surface, mid_uv)[0]
        else:
            mid = 0.5 * (nodes[a] + nodes[b])
        new = len(nodes) + np.arange(len(split))
        nodes = np.concatenate([nodes, mid])
        uv = np.concatenate([uv, mid_uv])
        tri[split] = np.column_stack([a, new, c])
        tri = np.concatenate([tri, np.column_stack([new, b, c])])
    return nodes, uv, tri
