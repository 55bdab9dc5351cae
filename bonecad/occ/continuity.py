"""Continuity across the seams between faces, and inside spline faces from their knots.

Across every edge shared by two faces, at ``samples`` parameters along it, the
two faces are evaluated at the points their own p-curves give:

- **G0**: distance between the two surface points (mm);
- **G1**: angle between the two outward normals (degrees);
- **G2**: normal curvature of each face in the direction across the edge
  (t_cross = n x t_edge, in the tangent plane), compared as the relative jump
  |k1 - k2| / max(|k1|, |k2|, 1 / curvature_radius_ref_mm).

Each seam is classed by its worst sample (thresholds in
:class:`ContinuityTolerances`): ``"gap"`` (G0 fails), ``"C0"`` (closed but G1
fails), ``"G1"`` (tangent-continuous, G2 fails), ``"G2"``.

Inside a B-spline face, a knot of multiplicity m in a direction of degree p
makes the surface C^(p-m) there (parametric continuity; geometric continuity
can be higher if poles happen to line up). Bezier faces have no interior knots.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bonecad.errors import InputError, KernelError
from bonecad.occ.tessellate import shape_faces

#: seam classes, worst first
CLASSES = ("gap", "C0", "G1", "G2")


@dataclass(frozen=True)
class ContinuityTolerances:
    """Thresholds of the seam classes (``[analysis]`` settings); the reason for each is given.

    gap_mm : 0.01 mm, the sewing tolerance of the NURBS baseline (defaults.toml
        [nurbs]) and 10x below the deviation bands: smaller gaps are closed.
    angle_deg : 0.1 degree; CAD systems' usual tangency tolerance is 0.1-1 deg,
        and an exactly G1 join measures ~1e-6 deg.
    curvature_jump : 0.05, a 5 % relative jump of normal curvature; an
        exactly G2 join measures ~1e-8.
    curvature_radius_ref_mm : 1000 mm; curvatures below 1/1000 mm^-1 count as
        flat, so a jump between two nearly flat faces is not magnified.
    """

    gap_mm: float
    angle_deg: float
    curvature_jump: float
    curvature_radius_ref_mm: float


@dataclass(frozen=True)
class SeamContinuity:
    """Per shared edge (E edges, S samples each).

    faces : (E, 2) int, indices (in ``shape_faces`` order) of the two faces
    length_mm : (E,)
    gap_mm, angle_deg, curvature_jump : (E, S) per sample
    classes : (E,) str, worst class along the edge
    face_names : the name of every face (``shape_faces`` order) when the model
        names them; the summary then counts the classes per pair of face names
    """

    faces: np.ndarray
    length_mm: np.ndarray
    gap_mm: np.ndarray
    angle_deg: np.ndarray
    curvature_jump: np.ndarray
    classes: np.ndarray
    tolerances: ContinuityTolerances
    face_names: tuple[str, ...] | None = None

    def pair_names(self) -> list[str]:
        """'a|b' (sorted) for every edge: the names of its two faces."""
        if self.face_names is None:
            raise InputError("the faces of this shape have no names")
        return ["|".join(sorted((self.face_names[a], self.face_names[b]))) for a, b in self.faces]

    def summary(self) -> dict:
        counts = {name: int(np.sum(self.classes == name)) for name in CLASSES}
        worst = next((name for name in CLASSES if counts[name]), "G2") if len(self.classes) else "none"
        by_pair = None
        if self.face_names is not None:
            pairs = np.array(self.pair_names(), dtype=object)
            by_pair = {p: {name: int(np.sum((pairs == p) & (self.classes == name))) for name in CLASSES}
                       for p in sorted(set(pairs.tolist()))}
        return {
            "edges": int(len(self.classes)),
            "class_counts": counts,
            "class_counts_by_face_pair": by_pair,
            "worst_class": worst,
            "max_gap_mm": float(self.gap_mm.max()) if self.gap_mm.size else 0.0,
            "max_angle_deg": float(self.angle_deg.max()) if self.angle_deg.size else 0.0,
            "max_curvature_jump": float(self.curvature_jump.max()) if self.curvature_jump.size else 0.0,
            "tolerances": {
                "gap_mm": self.tolerances.gap_mm,
                "angle_deg": self.tolerances.angle_deg,
                "curvature_jump": self.tolerances.curvature_jump,
                "curvature_radius_ref_mm": self.tolerances.curvature_radius_ref_mm,
            },
        }

    def to_dict(self) -> dict:
        return {
            "summary": self.summary(),
            "edges": [
                {
                    "faces": self.faces[i].tolist(),
                    **({} if self.face_names is None else
                       {"face_names": [self.face_names[k] for k in self.faces[i]]}),
                    "length_mm": float(self.length_mm[i]),
                    "max_gap_mm": float(self.gap_mm[i].max()),
                    "max_angle_deg": float(self.angle_deg[i].max()),
                    "max_curvature_jump": float(self.curvature_jump[i].max()),
                    "class": str(self.classes[i]),
                }
                for i in range(len(self.classes))
            ],
        }


@dataclass(frozen=True)
class KnotContinuity:
    """Continuity inside one spline face, per parameter direction.

    face : index; kind : 'bspline' | 'bezier' | 'other'
    degree : (2,) int (u, v); periodic : (2,) bool
    min_continuity : (2,) int, lowest C^k at any interior knot (or the periodic seam);
        equal to the degree's smoothness (a large number, 99) when there is none
    low_knots : per direction, list of (knot, multiplicity, C^k) below C2
    """

    face: int
    kind: str
    degree: np.ndarray
    periodic: np.ndarray
    min_continuity: np.ndarray
    low_knots: tuple[list, list] = field(default_factory=lambda: ([], []))

    def to_dict(self) -> dict:
        return {
            "face": self.face,
            "kind": self.kind,
            "degree": self.degree.tolist(),
            "periodic": self.periodic.tolist(),
            "min_continuity": self.min_continuity.tolist(),
            "low_knots": [[list(k) for k in d] for d in self.low_knots],
        }


#: C^k reported where there is no interior knot (a polynomial piece is C-infinity)
SMOOTH = 99


def _classify(gap, angle, jump, tol: ContinuityTolerances) -> str:
    if gap > tol.gap_mm:
        return "gap"
    if angle > tol.angle_deg:
        return "C0"
    if jump > tol.curvature_jump:
        return "G1"
    return "G2"


def _face_props(face, uv: np.ndarray):
    """Points (S, 3) and derivatives (S, 5, 3): D1U, D1V, D2U, D2V, DUV at uv (S, 2), by OpenCascade."""
    from OCP.BRepAdaptor import BRepAdaptor_Surface
    from OCP.BRepLProp import BRepLProp_SLProps

    props = BRepLProp_SLProps(BRepAdaptor_Surface(face), 2, 1e-9)
    out = np.empty((len(uv), 6, 3))
    for i, (u, v) in enumerate(uv):
        props.SetParameters(float(u), float(v))
        for k, vec in enumerate((props.Value(), props.D1U(), props.D1V(), props.D2U(), props.D2V(), props.DUV())):
            out[i, k] = vec.X(), vec.Y(), vec.Z()
    return out[:, 0], out[:, 1:]


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


def _pcurve_samples(edge, face, ts: np.ndarray):
    """(u, v) and d(u, v)/dt of ``edge``'s p-curve on ``face`` at edge parameters ``ts`` (S,).

    A straight p-curve (iso-lines of spline patches) is evaluated in numpy after
    checking its two end samples against OpenCascade; any other curve sample by sample.
    """
    from OCP.BRepAdaptor import BRepAdaptor_Curve2d
    from OCP.GeomAbs import GeomAbs_Line
    from OCP.gp import gp_Pnt2d, gp_Vec2d

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


def _face_surfaces(faces, tessellation) -> tuple:
    """A SurfaceSet of the faces and a mask of those evaluated from it (native spline faces).

    Native faces lie on their B-spline/Bezier surface with the face's own
    parameters, so p-curve (u, v) evaluate directly; others go through OpenCascade.
    """
    from bonecad.splines.evaluate import SurfaceSet
    from bonecad.occ.tessellate import face_spline_surface

    if tessellation is not None:
        if tessellation.face_count != len(faces):
            raise InputError(
                f"tessellation has {tessellation.face_count} faces, the shape {len(faces)}: not its tessellation"
            )
        sset = tessellation.surface_set
        native = np.asarray(tessellation.native_faces, dtype=bool) & (sset.group >= 0)
        return sset, native
    pairs = [face_spline_surface(face) for face in faces]
    sset = SurfaceSet([surface if native else None for surface, native in pairs])
    return sset, sset.group >= 0


def seam_continuity(
    shape, *, tolerances: ContinuityTolerances, samples: int = 21, tessellation=None,
    face_names: list[tuple[str, object]] | None = None,
) -> SeamContinuity:
    """G0/G1/G2 measures along every edge of ``shape`` shared by two different faces.

    Degenerate edges and seams of one periodic face are skipped (the latter's
    continuity is the face's own: see :func:`knot_continuity`). Spline faces
    are evaluated in one batch (``nurbs_eval.SurfaceSet``, second derivatives
    included); ``tessellation``, a :class:`~.tessellation.Tessellation` of
    ``shape``, lends its surfaces (else they are read from the faces).
    face_names : (name, TopoDS_Face) of every face, as the model stage names them.
    """
    from OCP.BRep import BRep_Tool
    from OCP.BRepAdaptor import BRepAdaptor_Curve
    from OCP.GCPnts import GCPnts_AbscissaPoint
    from OCP.TopAbs import TopAbs_EDGE, TopAbs_REVERSED
    from OCP.TopExp import TopExp
    from OCP.TopoDS import TopoDS
    from OCP.TopTools import TopTools_IndexedMapOfShape

    from bonecad.occ.brep import names_in_order

    tol = tolerances
    if samples < 2:
        raise InputError(f"samples must be >= 2, got {samples}")
    faces = shape_faces(shape)
    names = None if face_names is None else tuple(names_in_order(faces, face_names))
    edge_map = TopTools_IndexedMapOfShape()
    TopExp.MapShapes_s(shape, TopAbs_EDGE, edge_map)
    # edge -> the faces holding it, each with the edge as that face holds it (first occurrence:
    # a seam edge appears twice in its face); explored face by face, since iterating the
    # ancestor lists of MapShapesAndAncestors from Python is ~100x slower
    holders: dict[int, dict[int, object]] = {}
    for k, face in enumerate(faces):
        for e in _face_edges(face):
            holders.setdefault(edge_map.FindIndex(e), {}).setdefault(k, e)
    sset, batched = _face_surfaces(faces, tessellation)
    reversed_faces = np.array([face.Orientation() == TopAbs_REVERSED for face in faces])
    fraction = np.linspace(0.01, 0.99, samples)  # interior samples, the ends pulled in (ends meet corners)
    pairs, lengths, sample_face, sample_uv, sample_duv = [], [], [], [], []
    for i in sorted(holders):
        if len(holders[i]) != 2:
            continue  # free edge, seam of one face, or non-manifold
        edge = TopoDS.Edge_s(edge_map.FindKey(i))
        if BRep_Tool.Degenerated_s(edge):
            continue
        curve = BRepAdaptor_Curve(edge)
        t0, t1 = curve.FirstParameter(), curve.LastParameter()
        ts = t0 + (t1 - t0) * fraction
        index = list(holders[i])
        for k in index:
            uv, duv = _pcurve_samples(TopoDS.Edge_s(holders[i][k]), faces[k], ts)
            sample_face.append(np.full(samples, k))
            sample_uv.append(uv)
            sample_duv.append(duv)
        pairs.append(index)
        lengths.append(GCPnts_AbscissaPoint.Length_s(curve))
    if not pairs:
        empty = np.zeros((0, samples))
        return SeamContinuity(np.zeros((0, 2), int), np.zeros(0), empty, empty, empty, np.zeros(0, dtype=object), tol,
                              names)
    face_of = np.concatenate(sample_face)
    uv = np.concatenate(sample_uv)
    duv = np.concatenate(sample_duv)
    point = np.empty((len(face_of), 3))
    derivs = np.empty((len(face_of), 5, 3))  # S_u, S_v, S_uu, S_vv, S_uv
    fast = batched[face_of]
    if fast.any():
        s, su, sv, suu, svv, suv = sset.evaluate2(face_of[fast], uv[fast, 0], uv[fast, 1])
        point[fast] = s
        derivs[fast] = np.stack([su, sv, suu, svv, suv], axis=1)
    for k in np.unique(face_of[~fast]):
        sel = np.flatnonzero((face_of == k) & ~fast)
        point[sel], derivs[sel] = _face_props(faces[k], uv[sel])
    normal = _unit(np.cross(derivs[:, 0], derivs[:, 1]))
    normal[reversed_faces[face_of]] *= -1.0
    edges = len(pairs)
    point, normal, derivs = (a.reshape(edges, 2, samples, *a.shape[1:]) for a in (point, normal, derivs))
    # the edge's tangent from the first face: S_u u' + S_v v' along its p-curve
    duv = duv.reshape(edges, 2, samples, 2)
    tangents = _unit(
        (duv[:, 0, :, :1] * derivs[:, 0, :, 0] + duv[:, 0, :, 1:] * derivs[:, 0, :, 1]).reshape(-1, 3)
    )
    n1, n2 = normal[:, 0].reshape(-1, 3), normal[:, 1].reshape(-1, 3)
    gap = np.linalg.norm(point[:, 0] - point[:, 1], axis=2)
    angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n1, n2), -1.0, 1.0))).reshape(edges, samples)
    # each face's own direction across the edge (they coincide when G1 holds)
    k1 = _normal_curvature(derivs[:, 0].reshape(-1, 5, 3), n1, _unit(np.cross(n1, tangents)))
    k2 = _normal_curvature(derivs[:, 1].reshape(-1, 5, 3), n2, _unit(np.cross(n2, tangents)))
    scale = np.maximum(np.maximum(np.abs(k1), np.abs(k2)), 1.0 / tol.curvature_radius_ref_mm)
    jump = (np.abs(k1 - k2) / scale).reshape(edges, samples)
    classes = np.array(
        [_classify(g, a, j, tol) for g, a, j in zip(gap.max(axis=1), angle.max(axis=1), jump.max(axis=1))],
        dtype=object,
    )
    return SeamContinuity(
        faces=np.array(pairs, dtype=np.int64),
        length_mm=np.array(lengths),
        gap_mm=gap,
        angle_deg=angle,
        curvature_jump=jump,
        classes=classes,
        tolerances=tol,
        face_names=names,
    )


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)


def _face_edges(face):
    from OCP.TopAbs import TopAbs_EDGE
    from OCP.TopExp import TopExp_Explorer

    explorer = TopExp_Explorer(face, TopAbs_EDGE)
    while explorer.More():
        yield explorer.Current()
        explorer.Next()


def knot_continuity(shape) -> list[KnotContinuity]:
    """Continuity inside each face from its knot multiplicities (module doc)."""
    from OCP.BRep import BRep_Tool
    from OCP.Geom import Geom_BezierSurface, Geom_BSplineSurface, Geom_RectangularTrimmedSurface

    results = []
    for index, face in enumerate(shape_faces(shape)):
        surf = BRep_Tool.Surface_s(face)
        while isinstance(surf, Geom_RectangularTrimmedSurface):
            surf = surf.BasisSurface()
        if isinstance(surf, Geom_BSplineSurface):
            degree = np.array([surf.UDegree(), surf.VDegree()])
            periodic = np.array([surf.IsUPeriodic(), surf.IsVPeriodic()])
            low: tuple[list, list] = ([], [])
            mins = []
            for d, (knots, mults) in enumerate(
                ((surf.UKnots(), surf.UMultiplicities()), (surf.VKnots(), surf.VMultiplicities()))
            ):
                values = [knots.Value(i) for i in range(knots.Lower(), knots.Upper() + 1)]
                mult = [mults.Value(i) for i in range(mults.Lower(), mults.Upper() + 1)]
                # interior knots; for a periodic direction the first knot is the seam
                interior = range(0, len(values) - 1) if periodic[d] else range(1, len(values) - 1)
                conts = []
                for i in interior:
                    c = int(degree[d] - mult[i])
                    conts.append(c)
                    if c < 2:
                        low[d].append((float(values[i]), int(mult[i]), c))
                mins.append(min(conts) if conts else SMOOTH)
            results.append(KnotContinuity(index, "bspline", degree, periodic, np.array(mins), low))
        elif isinstance(surf, Geom_BezierSurface):
            degree = np.array([surf.UDegree(), surf.VDegree()])
            results.append(
                KnotContinuity(index, "bezier", degree, np.zeros(2, bool), np.array([SMOOTH, SMOOTH]))
            )
        else:
            results.append(
                KnotContinuity(index, "other", np.zeros(2, int), np.zeros(2, bool), np.array([SMOOTH, SMOOTH]))
            )
    if not results:
        raise KernelError("no faces to analyse")
    return results
