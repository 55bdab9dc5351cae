"""Continuity across the seams between faces, and inside spline faces from their knots.

Along every edge shared by two faces (sampled by :mod:`bonecad.occ.seams`):

- **G0**: distance between the two surface points (mm);
- **G1**: angle between the two outward normals (degrees);
- **G2**: normal curvature of each face in the direction across the edge,
  compared as the relative jump |k1 - k2| / max(|k1|, |k2|, 1 / curvature_radius_ref_mm).

Each seam is classed by its worst sample (thresholds in
:class:`ContinuityTolerances`): ``"gap"`` (G0 fails), ``"C0"`` (closed but G1
fails), ``"G1"`` (tangent-continuous, G2 fails), ``"G2"``.

Inside a B-spline face, a knot of multiplicity m in a direction of degree p
makes the surface C^(p-m) there (parametric continuity; geometric continuity
can be higher if poles happen to line up). Bezier faces have no interior knots.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np


if TYPE_CHECKING:  # OpenCascade is imported when a shape is analysed, not with the package
    from bonecad.occ.seams import FaceKnots, SeamSamples

log = logging.getLogger(__name__)

#: seam classes, worst first
CLASSES = ("gap", "C0", "G1", "G2")

#: C^k reported where there is no interior knot (a polynomial piece is C-infinity)
SMOOTH = 99


@dataclass(frozen=True)
class ContinuityTolerances:
    """Thresholds of the seam classes; the reason for each is given.

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

    faces : (E, 2) int, indices (in ``brep.faces`` order) of the two faces
    length_mm : (E,)
    gap_mm, angle_deg, curvature_jump : (E, S) per sample
    classes : (E,) str, worst class along the edge
    face_names : the name of every face (``brep.faces`` order) when the model
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
            raise ValueError("the faces of this shape have no names")
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


def seam_continuity(
    shape, *, tolerances: ContinuityTolerances, samples: int = 21, tessellation=None,
    face_names: list[tuple[str, object]] | None = None,
) -> SeamContinuity:
    """G0/G1/G2 measures along every edge of ``shape`` (a TopoDS_Shape) shared by two different faces.

    ``tessellation``, a :class:`~bonecad.mesh.tessellation.Tessellation` of ``shape``,
    lends its spline surfaces (:func:`bonecad.occ.seams.sample_seams`).
    face_names : (name, TopoDS_Face) of every face, as the model stage names them.
    """
    from bonecad.occ.brep import faces, names_in_order
    from bonecad.occ.seams import sample_seams

    seams = sample_seams(shape, samples=samples, tessellation=tessellation)
    names = None if face_names is None else tuple(names_in_order(faces(shape), face_names))
    return classify_seams(seams, tolerances, names)


def classify_seams(
    seams: SeamSamples, tolerances: ContinuityTolerances, face_names: tuple[str, ...] | None = None
) -> SeamContinuity:
    """Gap, normal angle and curvature jump at every sample of ``seams``, and each seam's worst class."""
    edge_count, _, samples = seams.curvatures.shape
    point, normal = seams.points, seams.normals
    n1, n2 = normal[:, 0].reshape(-1, 3), normal[:, 1].reshape(-1, 3)
    gap = np.linalg.norm(point[:, 0] - point[:, 1], axis=2)
    angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n1, n2), -1.0, 1.0))).reshape(edge_count, samples)
    k1, k2 = seams.curvatures[:, 0], seams.curvatures[:, 1]
    scale = np.maximum(np.maximum(np.abs(k1), np.abs(k2)), 1.0 / tolerances.curvature_radius_ref_mm)
    jump = np.abs(k1 - k2) / scale
    classes = np.array(
        [_classify(g, a, j, tolerances) for g, a, j in zip(gap.max(axis=1), angle.max(axis=1), jump.max(axis=1))],
        dtype=object,
    )
    return SeamContinuity(
        faces=seams.faces,
        length_mm=seams.length_mm,
        gap_mm=gap,
        angle_deg=angle,
        curvature_jump=jump,
        classes=classes,
        tolerances=tolerances,
        face_names=face_names,
    )


def _classify(gap: float, angle: float, jump: float, tol: ContinuityTolerances) -> str:
    if gap > tol.gap_mm:
        return "gap"
    if angle > tol.angle_deg:
        return "C0"
    if jump > tol.curvature_jump:
        return "G1"
    return "G2"


def knot_continuity(shape) -> list[KnotContinuity]:
    """Continuity inside each face of ``shape`` from its knot multiplicities (module doc)."""
    from bonecad.occ.seams import face_knots

    return [_knot_continuity(index, knots) for index, knots in enumerate(face_knots(shape))]


def _knot_continuity(index: int, face: FaceKnots) -> KnotContinuity:
    if face.kind != "bspline":
        return KnotContinuity(index, face.kind, face.degree, face.periodic, np.array([SMOOTH, SMOOTH]))
    low: tuple[list, list] = ([], [])
    mins = []
    for d in (0, 1):
        values, mult = face.knots[d], face.multiplicities[d]
        # interior knots; for a periodic direction the first knot is the seam
        interior = range(0, len(values) - 1) if face.periodic[d] else range(1, len(values) - 1)
        conts = []
        for i in interior:
            c = int(face.degree[d] - mult[i])
            conts.append(c)
            if c < 2:
                low[d].append((float(values[i]), int(mult[i]), c))
        mins.append(min(conts) if conts else SMOOTH)
    return KnotContinuity(index, "bspline", face.degree, face.periodic, np.array(mins), low)
