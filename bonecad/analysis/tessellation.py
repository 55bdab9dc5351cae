"""Fine tessellation of an OpenCascade shape, checked against the exact face areas.

This is the one place where the analysis reads OpenCascade geometry into numpy:
triangle nodes, their (u, v) on each face, and each face's surface as a
:class:`~bonecad.analysis.nurbs_eval.SplineSurface` for exact refinement.

Pitfall handled (DESIGN.md): ``BRepMesh_IncrementalMesh`` can cover only part of
a large periodic B-spline face. Every face's triangulated area is compared with
its exact area from ``BRepGProp.SurfaceProperties_s`` with an explicit relative
tolerance (adaptive Gauss integration); a face short by more than
``coverage_tolerance`` raises :class:`~bonecad.errors.KernelError`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError, KernelError
from .closest import vertex_normals
from .nurbs_eval import SplineSurface, project


@dataclass(frozen=True)
class TessellationSettings:
    """Tolerances of the tessellation (mm, rad); the reason for each default is given.

    deflection_mm : chord error asked of BRepMesh. 0.02 mm is 5x below the
        0.1 mm deviation band, so the KD-tree first guess lands within a few
        microns of parameter space of the foot point and Newton needs 2-3 steps.
    angular_deflection_rad : 0.2 rad keeps triangles on tight apex caps small.
    coverage_tolerance : relative area shortfall accepted per face. A chordal
        tessellation is short by about deflection/radius (1e-3 for 0.02 mm on a
        20 mm radius); 0.5 % leaves margin for that and still catches the
        known partial-coverage failure (20 % missing).
    area_rel_eps : relative error asked of BRepGProp's adaptive integration
        (default settings were 1 % off on large B-spline faces).
    max_edge_mm : triangles with a longer edge are bisected (new nodes on the
        exact surface). BRepMesh leaves long slivers along flat directions (a
        shaft, a cylinder); the closest-point search assumes compact triangles.
        1 mm keeps a tibia near 10^5 triangles.
    """

    deflection_mm: float = 0.02
    angular_deflection_rad: float = 0.2
    coverage_tolerance: float = 0.005
    area_rel_eps: float = 1e-6
    max_edge_mm: float = 1.0


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
        (centroids and edge midpoints) and the exact surface
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
    chord_error_mm: np.ndarray
    faces: tuple  # TopoDS_Face, in the order of the face index

    @property
    def face_count(self) -> int:
        return len(self.faces)

    def triangle_areas(self) -> np.ndarray:
        tri = self.vertices[self.triangles]
        return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def shape_faces(shape) -> list:
    """The faces of ``shape`` in explorer order (orientation as seen in the shape)."""
    from OCP.TopAbs import TopAbs_FACE
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    if shape is None or shape.IsNull():
        raise InputError("shape is null")
    faces = []
    explorer = TopExp_Explorer(shape, TopAbs_FACE)
    while explorer.More():
        faces.append(TopoDS.Face_s(explorer.Current()))
        explorer.Next()
    if not faces:
        raise InputError("shape has no faces")
    return faces


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
    knots_u = np.array(list(bs.UKnotSequence()), dtype=np.float64)
    knots_v = np.array(list(bs.VKnotSequence()), dtype=np.float64)
    nu, nv = bs.NbUPoles(), bs.NbVPoles()
    poles = np.empty((nu, nv, 4))
    for i in range(1, nu + 1):
        for j in range(1, nv + 1):
            p = bs.Pole(i, j)
            w = bs.Weight(i, j)
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


def tessellate(shape, settings: TessellationSettings | None = None) -> Tessellation:
    """Tessellate ``shape`` (any TopoDS_Shape with faces) and read it into numpy.

    Raises KernelError when BRepMesh fails or leaves a face covered short of its
    exact area by more than ``settings.coverage_tolerance``.
    """
    from OCP.BRep import BRep_Tool
    from OCP.BRepMesh import BRepMesh_IncrementalMesh
    from OCP.TopAbs import TopAbs_REVERSED
    from OCP.TopLoc import TopLoc_Location

    settings = settings or TessellationSettings()
    if settings.deflection_mm <= 0:
        raise InputError(f"deflection_mm must be > 0, got {settings.deflection_mm}")
    faces = shape_faces(shape)
    mesher = BRepMesh_IncrementalMesh(
        shape, settings.deflection_mm, False, settings.angular_deflection_rad, True
    )
    if not mesher.IsDone():
        raise KernelError("BRepMesh_IncrementalMesh failed on the shape")
    verts, tris, uvs, node_face, tri_face = [], [], [], [], []
    area_exact, area_mesh, surfaces, reversed_faces = [], [], [], []
    offset = 0
    for index, face in enumerate(faces):
        loc = TopLoc_Location()
        poly = BRep_Tool.Triangulation_s(face, loc)
        if poly is None or poly.NbTriangles() == 0:
            raise KernelError(f"face {index} has no triangulation after BRepMesh")
        trsf = loc.Transformation()
        nodes = np.array(
            [
                (p.X(), p.Y(), p.Z())
                for p in (poly.Node(i).Transformed(trsf) for i in range(1, poly.NbNodes() + 1))
            ]
        )
        uv = np.array(
            [(q.X(), q.Y()) for q in (poly.UVNode(i) for i in range(1, poly.NbNodes() + 1))]
        )
        tri = np.array([poly.Triangle(i).Get() for i in range(1, poly.NbTriangles() + 1)]) - 1
        is_reversed = face.Orientation() == TopAbs_REVERSED
        if is_reversed:
            tri = tri[:, [0, 2, 1]]
        t = nodes[tri]
        mesh_area = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum()
        exact = exact_face_area(face, settings.area_rel_eps)
        if exact > 0 and (exact - mesh_area) / exact > settings.coverage_tolerance:
            raise KernelError(
                f"face {index}: tessellation covers {mesh_area:.4g} mm^2 of {exact:.4g} mm^2 "
                f"({100 * mesh_area / exact:.2f} %); refusing a tessellation-based distance"
            )
        surface, native = face_spline_surface(face)
        if surface is not None and not native:
            uv = _native_to_spline_uv(face, surface, uv, nodes)
        nodes, uv, tri = _bisect_long_edges(nodes, uv, tri, surface, settings.max_edge_mm)
        verts.append(nodes)
        tris.append(tri + offset)
        uvs.append(uv)
        node_face.append(np.full(len(nodes), index))
        tri_face.append(np.full(len(tri), index))
        area_exact.append(exact)
        area_mesh.append(mesh_area)
        surfaces.append(surface)
        reversed_faces.append(is_reversed)
        offset += len(nodes)
    vertices = np.concatenate(verts)
    triangles = np.concatenate(tris)
    uv_all = np.concatenate(uvs)
    node_face_all = np.concatenate(node_face)
    tri_face_all = np.concatenate(tri_face)
    reversed_arr = np.array(reversed_faces, dtype=bool)
    normals = np.zeros_like(vertices)
    chord = np.zeros(len(faces))
    for index, surface in enumerate(surfaces):
        sel = node_face_all == index
        if surface is None:
            continue
        _, su, sv = _eval(surface, uv_all[sel])
        n = np.cross(su, sv)
        size = np.linalg.norm(n, axis=1, keepdims=True)
        # degenerate points (poles, collapsed rows): no surface normal; left to the mesh below
        good = size[:, 0] > 1e-10 * np.linalg.norm(su, axis=1) * np.linalg.norm(sv, axis=1)
        n = np.where(good[:, None], n / np.maximum(size, 1e-300), 0.0)
        normals[sel] = -n if reversed_arr[index] else n
        chord[index] = _chord_error(surface, vertices, uv_all, triangles[tri_face_all == index])
    # faces without a spline: area-weighted triangle normals at the nodes
    missing = np.linalg.norm(normals, axis=1) == 0
    if missing.any():
        normals[missing] = vertex_normals(vertices, triangles)[missing]
    return Tessellation(
        vertices=vertices,
        triangles=triangles,
        uv=uv_all,
        normals=normals,
        node_face=node_face_all,
        triangle_face=tri_face_all,
        face_area_exact_mm2=np.array(area_exact),
        face_area_mesh_mm2=np.array(area_mesh),
        surfaces=tuple(surfaces),
        reversed_faces=reversed_arr,
        chord_error_mm=chord,
        faces=tuple(faces),
    )


def _eval(surface: SplineSurface, uv: np.ndarray):
    from .nurbs_eval import evaluate

    return evaluate(surface, uv[:, 0], uv[:, 1])


def _chord_error(surface: SplineSurface, vertices, uv, triangles) -> float:
    """Largest distance from triangle centroids and edge midpoints to the surface (mm).

    Sampled at the centroid, the edge midpoints and the circumcentre (where the
    chord error of a triangle on a sphere peaks): a measured value, by exact
    projection, not BRepMesh's requested deflection (which BRepMesh exceeds
    by 2x on spheres).
    """
    if len(triangles) == 0:
        return 0.0
    weights = np.array(
        [[1 / 3, 1 / 3, 1 / 3], [0.5, 0.5, 0.0], [0.0, 0.5, 0.5], [0.5, 0.0, 0.5]]
    )
    t = vertices[triangles]
    # circumcentre of acute triangles: where the chord error of a triangle
    # inscribed in a sphere (the osculating surface) peaks; for an obtuse one
    # it is the middle of the longest edge, sampled already
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
    proj = project(surface, pts, start)
    good = proj.residual_mm < 1e-6 + 1e-3 * np.linalg.norm(pts - proj.foot, axis=1)
    d = np.linalg.norm(pts - proj.foot, axis=1)
    return float(d[good].max()) if good.any() else float(d.max())


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
