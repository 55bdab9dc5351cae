"""The standard morphometric parameters of a femur, measured in its anatomical frame (issue 45).

Bone coordinates (``AnatomicalFrame.to_bone``): origin on the anatomical axis at the knee centre's level,
x lateral, y anterior, z proximal along the anatomical (shaft) axis; a left femur's are a mirror image, so
it measures as a right one. The landmarks are the frame's (``FemurLandmarks``: head sphere, neck axis,
shaft axis, the raters' landmarks of ``anatomy.femur_points``). ``PARAMETERS`` lists the names, units and
definitions; ``bonecad/data/femur_ranges.toml`` the published adult ranges (docs/guides/femur-landmarks.md).
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass
from importlib import resources

import numpy as np

from bonecad.anatomy.frame import AnatomicalFrame
from bonecad.errors import FitError
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.mesh.sections import polygon_centroid, section_mesh

#: shaft levels: shares (%) of the maximal length below the top of the head (20 % about the lesser
#: trochanter, 50 % mid-shaft), the convention of medullary canal studies
SHAFT_LEVELS = (20, 35, 50, 65, 80)
#: the anterior bow: a circle through the centroids of the transverse sections from 25 to 75 % of the
#: maximal length (the diaphysis, clear of the trochanters and the condyles), every 2.5 %: the shaft's
#: centreline (the anterior cortex's points gave 2409 mm on the LHDL femur, whose centreline bows at 1128 mm:
#: its anterior cortex thickens towards mid-shaft)
BOW_LEVELS = tuple(np.arange(25.0, 75.1, 2.5))

_SHAFT = tuple(
    (f"shaft_{d}_{pct}_mm", "mm", f"{name} diameter (caliper extent along the {axis} axis) of the transverse "
     f"section {pct} % of max_length_mm below the top of the head")
    for d, name, axis in (("ml", "medio-lateral", "lateral"), ("ap", "antero-posterior", "anterior"))
    for pct in SHAFT_LEVELS
)
_CANAL = tuple(
    (f"canal_ml_{pct}_mm", "mm", f"medio-lateral width of the medullary canal (the inner loop of the section at "
     f"{pct} %; empty when the mesh shows no canal: an outer surface only)")
    for pct in SHAFT_LEVELS
)

#: (name, unit, definition) of every parameter, in the order of ``FemurMeasurements.values()``
PARAMETERS: tuple[tuple[str, str, str], ...] = (
    ("max_length_mm", "mm", "extent of the bone along the anatomical axis (top of the head to the lowest "
     "condyle; the osteometric board's maximal length)"),
    ("mechanical_length_mm", "mm", "knee centre to head centre (the mechanical axis)"),
    ("head_diameter_mm", "mm", "diameter of the sphere fitted to the femoral head"),
    ("neck_length_mm", "mm", "head centre to the point of the neck axis nearest the anatomical axis (the neck "
     "axis: head centre -> centroid of the neck's narrowest section)"),
    ("neck_shaft_angle_deg", "deg", "angle between the neck axis (towards the head) and the anatomical axis "
     "(towards the knee)"),
    ("femoral_offset_mm", "mm", "distance of the head centre from the anatomical axis"),
    ("anteversion_deg", "deg", "in the plane across the anatomical axis, the angle from the posterior condylar "
     "line (PLC -> PMC, the condyles' most posterior points) to the neck axis (neck -> head); positive "
     "when the neck turns anteriorly"),
    ("condylar_width_mm", "mm", "epicondylar breadth: the distance between the epicondyles (LEC, MEC)"),
    ("anterior_bow_radius_mm", "mm", "radius of the circle fitted (least squares, sagittal plane) to the "
     "centroids of the transverse sections 25-75 % of max_length_mm below the top of the head (the shaft's "
     "centreline); positive when the shaft bows forwards"),
    *_SHAFT,
    *_CANAL,
)
PARAMETER_NAMES: tuple[str, ...] = tuple(name for name, _, _ in PARAMETERS)
#: the parameters whose left-right difference a contralateral template carries (``asymmetry``)
ASYMMETRY = ("max_length_mm", "anteversion_deg", "neck_shaft_angle_deg")


@dataclass(frozen=True)
class FemurMeasurements:
    """One femur's parameters (``PARAMETERS``: mm and degrees; NaN where the mesh does not show one, e.g. a
    canal), ``side`` of the input."""

    side: str
    measures: tuple[float, ...]  # in the order of PARAMETERS

    bone = "femur"
    parameters = PARAMETERS

    def values(self) -> dict[str, float]:
        """name -> value, in the order of ``PARAMETERS``."""
        return dict(zip(PARAMETER_NAMES, self.measures))


def measure_femur(bone: BoneMesh, frame: AnatomicalFrame) -> FemurMeasurements:
    """Measure a femur (its working copy, ``BoneMesh.work``) in its anatomical frame."""
    if frame.femur is None:
        raise FitError("the frame carries no femur landmarks")
    lm = frame.femur
    work = bone.work
    v = frame.to_bone(work.vertices)
    faces = work.faces[:, ::-1] if frame.mirrored else work.faces  # a mirror image: faces stay outward
    head = frame.to_bone(lm.head.centre[None])[0]
    neck_end = frame.to_bone(lm.neck_axis[1][None])[0]
    shaft = frame.to_bone(lm.shaft_axis)
    d = (shaft[1] - shaft[0]) / np.linalg.norm(shaft[1] - shaft[0])
    top = float(v[:, 2].max())
    m: dict[str, float] = {
        "max_length_mm": float(np.ptp(v[:, 2])),
        "mechanical_length_mm": frame.mechanical_length_mm,
        "head_diameter_mm": 2.0 * lm.head.radius_mm,
        "neck_shaft_angle_deg": lm.neck_shaft_angle_deg,
    }
    neck = (head - neck_end) / np.linalg.norm(head - neck_end)
    m["neck_length_mm"] = float(np.linalg.norm(head - _nearest_on_line(head, neck, shaft[0], d)))
    rel = head - shaft[0]
    m["femoral_offset_mm"] = float(np.linalg.norm(rel - (rel @ d) * d))
    points = {name: frame.to_bone(p[None])[0] for name, p in lm.points.items()}
    condylar = points["PMC"] - points["PLC"]
    m["anteversion_deg"] = anteversion_deg(condylar, neck, d)
    m["condylar_width_mm"] = float(np.linalg.norm(points["LEC"] - points["MEC"]))
    m["anterior_bow_radius_mm"] = _anterior_bow(v, faces, top, m["max_length_mm"])
    for pct in SHAFT_LEVELS:
        loops = _loops(v, faces, top - pct / 100.0 * m["max_length_mm"], f"the shaft at {pct} %")
        outer = loops[0]
        m[f"shaft_ml_{pct}_mm"] = float(np.ptp(outer[:, 0]))
        m[f"shaft_ap_{pct}_mm"] = float(np.ptp(outer[:, 1]))
        m[f"canal_ml_{pct}_mm"] = canal_width(loops)
    return FemurMeasurements(frame.side, tuple(float(m[name]) for name in PARAMETER_NAMES))


def anteversion_deg(condylar: np.ndarray, neck: np.ndarray, axis: np.ndarray) -> float:
    """Femoral anteversion (degrees) in bone coordinates: from ``condylar`` (lateral -> medial posterior
    condyle) to ``neck`` (towards the head), both projected across ``axis``; positive when the neck turns
    from the condylar line towards anterior (+y)."""
    def turn(w: np.ndarray) -> float:
        w = w - (w @ axis) * axis
        return float(np.arctan2(w[1], -w[0]))  # from medial (-x) towards anterior (+y)

    return float((np.degrees(turn(neck) - turn(condylar)) + 180.0) % 360.0 - 180.0)


def asymmetry(left: FemurMeasurements, right: FemurMeasurements) -> dict[str, float]:
    """Right minus left of the ``ASYMMETRY`` parameters (mm, degrees): what a contralateral template (the
    other side mirrored) carries."""
    lv, rv = left.values(), right.values()
    return {name: rv[name] - lv[name] for name in ASYMMETRY}


def published_ranges() -> dict[str, dict]:
    """name -> {"range": [lo, hi], "source": ...} of ``bonecad/data/femur_ranges.toml``."""
    text = resources.files("bonecad").joinpath("data/femur_ranges.toml").read_text()
    return tomllib.loads(text)["ranges"]


def canal_width(loops: list[np.ndarray]) -> float:
    """Medio-lateral width (mm) of the largest loop lying inside the largest of a section's (p, 2) loops (the
    medullary canal of a hollow surface); NaN when there is none."""
    inner = [lp for lp in loops[1:] if _inside(lp, loops[0])]
    return float(np.ptp(inner[0][:, 0])) if inner else float("nan")


def _nearest_on_line(p: np.ndarray, u: np.ndarray, q: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The point of the line p + s u nearest the line q + t d."""
    w = p - q
    a, b, c = u @ u, u @ d, d @ d
    denominator = a * c - b * b
    s = (b * (d @ w) - c * (u @ w)) / denominator if abs(denominator) > 1e-12 else 0.0
    return p + s * u


def _loops(v: np.ndarray, faces: np.ndarray, height: float, where: str) -> list[np.ndarray]:
    """(p, 2) x, y of the loops of the transverse section ``height`` mm above the origin, largest first."""
    loops = section_mesh(v, faces, np.array([0.0, 0.0, height]), np.array([0.0, 0.0, 1.0])).loops()
    if not loops:
        raise FitError(f"no transverse section through {where} ({height:.1f} mm above the knee centre)")
    return [lp[:, :2] for lp in loops]


def _inside(inner: np.ndarray, outer: np.ndarray) -> bool:
    """Whether a loop lies inside another (its first point, by ray crossings)."""
    x, y = inner[0]
    a, b = outer, np.roll(outer, -1, axis=0)
    crosses = ((a[:, 1] > y) != (b[:, 1] > y)) & (
        x < a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / np.where(b[:, 1] == a[:, 1], 1e-300, b[:, 1] - a[:, 1]))
    return bool(crosses.sum() % 2)


def _anterior_bow(v: np.ndarray, faces: np.ndarray, top: float, length: float) -> float:
    """Signed radius (mm) of the circle through the sections' centroids (``BOW_LEVELS``)."""
    pts = []
    for pct in BOW_LEVELS:
        z = top - pct / 100.0 * length
        outer = _loops(v, faces, z, f"the shaft at {pct:.1f} %")[0]
        pts.append((float(polygon_centroid(outer)[1]), z))
    y, z = np.array(pts).T
    # circle (y - a)^2 + (z - b)^2 = r^2, algebraic least squares
    design = np.column_stack([2 * y, 2 * z, np.ones_like(y)])
    a, b, c = np.linalg.lstsq(design, y**2 + z**2, rcond=None)[0]
    radius = float(np.sqrt(c + a * a + b * b))
    return radius if a < float(np.mean(y)) else -radius  # the centre behind the shaft: bowed forwards
