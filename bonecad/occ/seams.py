"""The seams and knots of a B-rep read into numpy: the OpenCascade half of the continuity analysis.

Across every edge shared by two different faces, at ``samples`` parameters
along it, each face is evaluated at the point its own p-curve gives: position,
outward normal, and normal curvature in the direction across the edge
(t_cross = n x t_edge, in the tangent plane). The knots of every spline face are
read as they are. :mod:`bonecad.analysis.continuity` classifies both.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from OCP.BRep import BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Curve, BRepAdaptor_Curve2d, BRepAdaptor_Surface
from OCP.BRepLProp import BRepLProp_SLProps
from OCP.GCPnts import GCPnts_AbscissaPoint
from OCP.Geom import Geom_BezierSurface, Geom_BSplineSurface, Geom_RectangularTrimmedSurface
from OCP.GeomAbs import GeomAbs_Line
from OCP.TopAbs import TopAbs_EDGE
from OCP.TopExp import TopExp
from OCP.TopoDS import TopoDS
from OCP.TopTools import TopTools_IndexedMapOfShape
from OCP.gp import gp_Pnt2d, gp_Vec2d

from bonecad.occ.brep import edges, face_is_reversed, nonempty_faces, read_array1
from bonecad.occ.read_faces import face_spline_surface
from bonecad.splines.surface import SurfaceSet

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SeamSamples:
    """Both faces along every seam: E edges shared by two different faces, S samples each.

    faces : (E, 2) int, indices (in ``brep.faces`` order) of the two faces
    length_mm : (E,) edge length
    points : (E, 2, S, 3) mm, each face's point at the sample
    normals : (E, 2, S, 3) unit outward normals (face orientation applied)
    curvatures : (E, 2, S) 1/mm, each face's normal curvature across the edge,
        signed with its outward normal
    """

    faces: np.ndarray
    length_mm: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    curvatures: np.ndarray


@dataclass(frozen=True)
class FaceKnots:
    """The surface of one face as far as its knots tell its continuity.

    kind : 'bspline' | 'bezier' | 'other'
    degree : (2,) int (u, v); zeros for 'other'
    periodic : (2,) bool
    knots, multiplicities : per direction (u, v), distinct knots (float) and their
        multiplicities (int); empty but for 'bspline'
    """

    kind: str
    degree: np.ndarray
    periodic: np.ndarray
    knots: tuple[np.ndarray, np.ndarray] = (np.zeros(0), np.zeros(0))
    multiplicities: tuple[np.ndarray, np.ndarray] = (np.zeros(0, int), np.zeros(0, int))


def sample_seams(shape, *, samples: int, tessellation=None) -> SeamSamples:
    """Both faces of every seam of ``shape`` at ``samples`` interior points of the edge (module doc).

    Degenerate edges and seams of one periodic face are skipped (the latter's
    continuity is the face's own: see :func:`face_knots`). Spline faces are
    evaluated in one batch (``SurfaceSet.evaluate``, order 2), others by OpenCascade;
    ``tessellation``, a :class:`~bonecad.mesh.tessellation.Tessellation` of
    ``shape``, lends its surfaces (else they are read from the faces).
    """
    if samples < 2:
        raise ValueError(f"samples must be >= 2, got {samples}")
    faces = nonempty_faces(shape)
    seams = _shared_edges(shape, faces)
    if not seams:
        return SeamSamples(np.zeros((0, 2), int), np.zeros(0), np.zeros((0, 2, samples, 3)),
                           np.zeros((0, 2, samples, 3)), np.zeros((0, 2, samples)))
    fraction = np.linspace(0.01, 0.99, samples)  # interior samples, the ends pulled in (ends meet corners)
    pairs, lengths, sample_face, sample_uv, sample_duv = [], [], [], [], []
    for edge, held in seams:
        curve = BRepAdaptor_Curve(edge)
        t0, t1 = curve.FirstParameter(), curve.LastParameter()
        ts = t0 + (t1 - t0) * fraction
        for k, own_edge in held.items():
            uv, duv = _pcurve_samples(own_edge, faces[k], ts)
            sample_face.append(np.full(samples, k))
            sample_uv.append(uv)
            sample_duv.append(duv)
        pairs.append(list(held))
        lengths.append(GCPnts_AbscissaPoint.Length_s(curve))
    face_of = np.concatenate(sample_face)
    point, derivs = _evaluate(faces, face_of, np.concatenate(sample_uv), tessellation)
    normal = _unit(np.cross(derivs[:, 0], derivs[:, 1]))
    normal[np.array([face_is_reversed(face) for face in faces])[face_of]] *= -1.0
    edge_count = len(pairs)
    point, normal, derivs = (a.reshape(edge_count, 2, samples, *a.shape[1:]) for a in (point, normal, derivs))
    duv = np.concatenate(sample_duv).reshape(edge_count, 2, samples, 2)
    return SeamSamples(
        faces=np.array(pairs, dtype=np.int64),
        length_mm=np.array(lengths),
        points=point,
        normals=normal,
        curvatures=_cross_curvatures(derivs, normal, duv),
    )


def _shared_edges(shape, faces: list) -> list[tuple[object, dict[int, object]]]:
    """(edge, {face index: the edge as that face holds it}) of every non-degenerate edge held by
    exactly two faces, in the order of the shape's edge map.

    The first occurrence counts (a seam edge appears twice in its face). Explored face by face,
    since iterating the ancestor lists of MapShapesAndAncestors from Python is ~100x slower.
    """
    edge_map = TopTools_IndexedMapOfShape()
    TopExp.MapShapes_s(shape, TopAbs_EDGE, edge_map)
    holders: dict[int, dict[int, object]] = {}
    for k, face in enumerate(faces):
        for edge in edges(face):
            holders.setdefault(edge_map.FindIndex(edge), {}).setdefault(k, edge)
    seams = []
    for i in sorted(holders):
        if len(holders[i]) != 2:
            continue  # free edge, seam of one face, or non-manifold
        edge = TopoDS.Edge_s(edge_map.FindKey(i))
        if not BRep_Tool.Degenerated_s(edge):
            seams.append((edge, holders[i]))
    return seams


def _pcurve_samples(edge, face, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) and d(u, v)/dt of ``edge``'s p-curve on ``face`` at edge parameters ``ts`` (S,).

    A straight p-curve (iso-lines of spline patches) is evaluated in numpy after
    checking its two end samples against OpenCascade; any other curve sample by sample.
    """
    pc = BRepAdaptor_Curve2d(edge, face)
    if pc.GetType() == GeomAbs_Line:
        line = pc.Line()
        loc, dirn = line.Location(), line.Direction()
        origin = np.array([loc.X(), loc.Y()])
        step = np.array([dirn.X(), dirn.Y()])
        uv = origin + ts[:, None] * step
        ends = np.array([(q.X(), q.Y()) for q in (pc.Value(float(ts[0])), pc.Value(float(ts[-1])))])
        scale = max(1.0, float(np.abs(uv).max()))
        if np.abs(ends - uv[[0, -1]]).max() <= 1e-12 * scale:
            return uv, np.broadcast_to(step, uv.shape)
    uv = np.empty((len(ts), 2))
    duv = np.empty((len(ts), 2))
    for s, t in enumerate(ts):
        p, d = gp_Pnt2d(), gp_Vec2d()
        pc.D1(float(t), p, d)
        uv[s] = p.X(), p.Y()
        duv[s] = d.X(), d.Y()
    return uv, duv


def _evaluate(faces: list, face_of: np.ndarray, uv: np.ndarray, tessellation) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) and derivatives (N, 5, 3): S_u, S_v, S_uu, S_vv, S_uv of faces ``face_of`` (N,) at ``uv``
    (N, 2): native spline faces in one batch, the others by OpenCascade."""
    sset, batched = _face_surfaces(faces, tessellation)
    point = np.empty((len(face_of), 3))
    derivs = np.empty((len(face_of), 5, 3))
    fast = batched[face_of]
    if fast.any():
        sample = sset.evaluate(face_of[fast], uv[fast, 0], uv[fast, 1], order=2)
        point[fast] = sample.points
        derivs[fast] = np.stack([sample.du, sample.dv, sample.duu, sample.dvv, sample.duv], axis=1)
    for k in np.unique(face_of[~fast]):
        sel = np.flatnonzero((face_of == k) & ~fast)
        point[sel], derivs[sel] = _face_props(faces[k], uv[sel])
    return point, derivs


def _face_surfaces(faces: list, tessellation) -> tuple[SurfaceSet, np.ndarray]:
    """A SurfaceSet of the faces and a mask of those evaluated from it (native spline faces).

    Native faces lie on their B-spline/Bezier surface with the face's own
    parameters, so p-curve (u, v) evaluate directly; others go through OpenCascade.
    """
    if tessellation is not None:
        if tessellation.face_count != len(faces):
            raise ValueError(
                f"tessellation has {tessellation.face_count} faces, the shape {len(faces)}: not its tessellation"
            )
        sset = tessellation.surface_set
        native = np.asarray(tessellation.native_faces, dtype=bool) & (sset.group >= 0)
        return sset, native
    pairs = [face_spline_surface(face) for face in faces]
    sset = SurfaceSet([surface if native else None for surface, native in pairs])
    return sset, sset.group >= 0


def _face_props(face, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (S, 3) and derivatives (S, 5, 3): D1U, D1V, D2U, D2V, DUV at uv (S, 2), by OpenCascade."""
    props = BRepLProp_SLProps(BRepAdaptor_Surface(face), 2, 1e-9)
    out = np.empty((len(uv), 6, 3))
    for i, (u, v) in enumerate(uv):
        props.SetParameters(float(u), float(v))
        for k, vec in enumerate((props.Value(), props.D1U(), props.D1V(), props.D2U(), props.D2V(), props.DUV())):
            out[i, k] = vec.X(), vec.Y(), vec.Z()
    return out[:, 0], out[:, 1:]


def _cross_curvatures(derivs: np.ndarray, normal: np.ndarray, duv: np.ndarray) -> np.ndarray:
    """(E, 2, S) normal curvature of each face across the edge, from derivatives (E, 2, S, 5, 3), outward
    normals (E, 2, S, 3) and the p-curves' d(u, v)/dt (E, 2, S, 2).

    The edge's tangent comes from the first face, S_u u' + S_v v' along its
    p-curve; each face then takes its own direction across the edge (the two
    coincide when G1 holds).
    """
    edge_count, _, samples = normal.shape[:3]
    tangents = _unit(
        (duv[:, 0, :, :1] * derivs[:, 0, :, 0] + duv[:, 0, :, 1:] * derivs[:, 0, :, 1]).reshape(-1, 3)
    )
    curvatures = []
    for side in (0, 1):
        n = normal[:, side].reshape(-1, 3)
        curvatures.append(_normal_curvature(derivs[:, side].reshape(-1, 5, 3), n, _unit(np.cross(n, tangents))))
    return np.stack(curvatures).reshape(2, edge_count, samples).swapaxes(0, 1)


def _normal_curvature(derivs: np.ndarray, normal: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Normal curvature (1/mm) in tangent ``direction``: k = II(d, d) / I(d, d).

    d = a S_u + b S_v (least squares in the tangent plane); II is taken with the
    oriented ``normal``, so both faces of a seam use the same sign convention.
    """
    su, sv, suu, svv, suv = (derivs[:, k] for k in range(5))
    e = np.einsum("ij,ij->i", su, su)
    f = np.einsum("ij,ij->i", su, sv)
    g = np.einsum("ij,ij->i", sv, sv)
    r1 = np.einsum("ij,ij->i", su, direction)
    r2 = np.einsum("ij,ij->i", sv, direction)
    det = e * g - f * f
    a = (g * r1 - f * r2) / det
    b = (e * r2 - f * r1) / det
    ll = np.einsum("ij,ij->i", suu, normal)
    mm = np.einsum("ij,ij->i", suv, normal)
    nn = np.einsum("ij,ij->i", svv, normal)
    first = e * a * a + 2 * f * a * b + g * b * b
    return (ll * a * a + 2 * mm * a * b + nn * b * b) / first


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)


def face_knots(shape) -> list[FaceKnots]:
    """The surface kind, degrees, periodicity and knots of every face of ``shape`` (``brep.faces`` order)."""
    out = []
    for face in nonempty_faces(shape):
        surf = BRep_Tool.Surface_s(face)
        while isinstance(surf, Geom_RectangularTrimmedSurface):
            surf = surf.BasisSurface()
        if isinstance(surf, Geom_BSplineSurface):
            out.append(FaceKnots(
                "bspline",
                np.array([surf.UDegree(), surf.VDegree()]),
                np.array([surf.IsUPeriodic(), surf.IsVPeriodic()]),
                (read_array1(surf.UKnots()), read_array1(surf.VKnots())),
                (read_array1(surf.UMultiplicities(), int), read_array1(surf.VMultiplicities(), int)),
            ))
        elif isinstance(surf, Geom_BezierSurface):
            out.append(FaceKnots("bezier", np.array([surf.UDegree(), surf.VDegree()]), np.zeros(2, bool)))
        else:
            out.append(FaceKnots("other", np.zeros(2, int), np.zeros(2, bool)))
    return out
