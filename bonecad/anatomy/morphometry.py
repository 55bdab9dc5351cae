"""The standard morphometric parameters of a tibia, measured in its anatomical frame.

Every measure is taken in bone coordinates (``AnatomicalFrame.to_bone``:
origin the plafond centre, x lateral, y anterior, z proximal along the
mechanical axis), where every tibia looks like a right one, so a left tibia
and its mirror image measure alike. ``PARAMETERS`` lists the names, units and
definitions (the README's table, the CLI's table and the JSON/CSV columns).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bonecad.anatomy.frame import AnatomicalFrame
from bonecad.errors import FitError
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.mesh.sections import hull_edge_across, line_crossings, polygon_centroid, section_mesh
from bonecad.settings import MorphometrySettings

#: shaft diameter levels: shares of ``length_mm`` above the plafond centre (from the distal end, Ruff's convention)
SHAFT_LEVELS = (20, 35, 50, 65, 80)

_SHAFT = tuple(
    (f"shaft_{d}_{pct}_mm", "mm", f"{name} diameter (caliper extent along the {axis} axis) of the transverse "
     f"section {pct} % of length_mm above the plafond centre")
    for d, name, axis in (("ml", "medio-lateral", "lateral"), ("ap", "antero-posterior", "anterior"))
    for pct in SHAFT_LEVELS
)

#: (name, unit, definition) of every parameter, in the order of ``TibiaMeasurements.values()``
PARAMETERS: tuple[tuple[str, str, str], ...] = (
    ("length_mm", "mm", "plateau centre to plafond centre (the mechanical axis of the frame)"),
    ("max_length_mm", "mm", "extent of the bone along the mechanical axis (intercondylar eminence to the tip "
     "of the medial malleolus)"),
    ("plateau_width_mm", "mm", "medio-lateral extent of the plateau section (transverse, [morphometry] "
     "plateau_section_depth_mm below the plateau centre)"),
    ("medial_plateau_depth_mm", "mm", "antero-posterior chord of the plateau section through the medial condyle "
     "centre (a quarter of the plateau width from its medial edge)"),
    ("lateral_plateau_depth_mm", "mm", "antero-posterior chord of the plateau section through the lateral "
     "condyle centre (a quarter of the plateau width from its lateral edge)"),
    ("medial_posterior_slope_deg", "deg", "in the sagittal section through the medial condyle centre, the angle "
     "between the line tangent to the plateau from above (across its anterior and posterior rims) and the "
     "plane perpendicular to the mechanical axis; positive when the plateau falls posteriorly"),
    ("lateral_posterior_slope_deg", "deg", "the same through the lateral condyle centre"),
    ("plafond_width_mm", "mm", "medio-lateral extent of the distal articular surface along the ankle's "
     "transverse axis (the torsion's distal line): the part of the vertical section through the plafond centre "
     "along that axis facing distally, within [morphometry] plafond_band_mm of the plafond's level"),
    ("plafond_depth_mm", "mm", "antero-posterior extent of the distal articular surface (the same in the "
     "vertical section across the ankle's transverse axis)"),
    ("bimalleolar_width_mm", "mm", "tibia alone (no fibula): extent of the distal tibia along the ankle's "
     "transverse axis, from the medial malleolus to the lateral border at the fibular notch, up to "
     "[morphometry] distal_zone_mm above the plafond centre"),
    *_SHAFT,
    ("torsion_deg", "deg", "tibial torsion on the tibia alone: angle in the transverse plane from the posterior "
     "condylar line of the plateau section (the tangent to both condyles' posterior borders) to the "
     "line from the centre of the medial malleolus (its section [morphometry] malleolus_depth_mm below the "
     "plafond centre) to the plafond centre; positive external (the distal end turned laterally)"),
)
PARAMETER_NAMES: tuple[str, ...] = tuple(name for name, _, _ in PARAMETERS)


@dataclass(frozen=True)
class TibiaMeasurements:
    """One tibia's parameters (``PARAMETERS``: mm and degrees), ``side`` of the input."""

    side: str
    measures: tuple[float, ...]  # in the order of PARAMETERS

    def values(self) -> dict[str, float]:
        """name -> value, in the order of ``PARAMETERS``."""
        return dict(zip(PARAMETER_NAMES, self.measures))


def measure_tibia(bone: BoneMesh, frame: AnatomicalFrame, settings: MorphometrySettings) -> TibiaMeasurements:
    """Measure a tibia (its working copy, ``BoneMesh.work``) in its anatomical frame."""
    work = bone.work
    v = frame.to_bone(work.vertices)
    # a left tibia's bone coordinates are a mirror image: turn its faces so they stay outward
    faces = work.faces[:, ::-1] if frame.mirrored else work.faces
    length = frame.mechanical_length_mm
    m: dict[str, float] = {"length_mm": length, "max_length_mm": float(np.ptp(v[:, 2]))}

    plateau = _outline(v, faces, length - settings.plateau_section_depth_mm, "plateau")
    x_lo, x_hi = float(plateau[:, 0].min()), float(plateau[:, 0].max())
    width = x_hi - x_lo
    m["plateau_width_mm"] = width
    condyles = {"medial": x_lo + settings.condyle_share * width, "lateral": x_hi - settings.condyle_share * width}
    chords = {side: _chord(plateau, 0, x, f"the {side} condyle") for side, x in condyles.items()}
    for side in ("medial", "lateral"):
        m[f"{side}_plateau_depth_mm"] = chords[side][1] - chords[side][0]
    for side in ("medial", "lateral"):
        m[f"{side}_posterior_slope_deg"] = _posterior_slope(v, faces, condyles[side], chords[side], length,
                                                            settings.slope_window_mm)

    # The ankle's own transverse axis: from the medial malleolus's centre to the plafond centre (the
    # distal line of the torsion); the plafond and bimalleolar widths run along it, the depth across it.
    malleolus = _malleolus_centre(v, faces, settings)
    ankle = np.array([-malleolus[0], -malleolus[1], 0.0]) / np.linalg.norm(malleolus)
    across = np.cross([0.0, 0.0, 1.0], ankle)  # anterior, turned with the ankle
    m["plafond_width_mm"] = _articular_extent(v, faces, ankle, settings)
    m["plafond_depth_mm"] = _articular_extent(v, faces, across, settings)
    distal = v[v[:, 2] < settings.distal_zone_mm]
    m["bimalleolar_width_mm"] = float(np.ptp(distal @ ankle))

    for pct in SHAFT_LEVELS:
        loop = _outline(v, faces, pct / 100.0 * length, f"the shaft at {pct} %")
        m[f"shaft_ml_{pct}_mm"] = float(np.ptp(loop[:, 0]))
        m[f"shaft_ap_{pct}_mm"] = float(np.ptp(loop[:, 1]))

    m["torsion_deg"] = torsion_deg(plateau, 0.5 * (condyles["medial"] + condyles["lateral"]), malleolus)
    return TibiaMeasurements(frame.side, tuple(float(m[name]) for name in PARAMETER_NAMES))


def _malleolus_centre(v: np.ndarray, faces: np.ndarray, settings: MorphometrySettings) -> np.ndarray:
    """(2,) x, y (bone coordinates, mm) of the medial malleolus's centre: its section's centroid
    ``malleolus_depth_mm`` below the plafond centre."""
    return polygon_centroid(_outline(v, faces, -settings.malleolus_depth_mm, "the medial malleolus"))


def ankle_turn_deg(bone: BoneMesh, frame: AnatomicalFrame, settings: MorphometrySettings) -> float:
    """Direction (degrees from lateral towards anterior, bone coordinates) of the ankle's own lateral axis,
    from the medial malleolus's centre through the plafond centre: where the distal end's lateral lies once
    the tibia's torsion has turned it (the template's angles follow it, ``tspline_model.template``)."""
    work = bone.work
    faces = work.faces[:, ::-1] if frame.mirrored else work.faces
    malleolus = _malleolus_centre(frame.to_bone(work.vertices), faces, settings)
    return float(np.degrees(np.arctan2(-malleolus[1], -malleolus[0])))


def tibial_tuberosity(bone: BoneMesh, frame: AnatomicalFrame, settings: MorphometrySettings) -> np.ndarray:
    """The tibial tuberosity (bone coordinates, mm): among the working copy's vertices in the band
    ``[morphometry] tuberosity_band`` (shares of the mechanical length) that lie in front of the axis
    (within 45 degrees of anterior), the one standing furthest in front of the line through the most anterior
    points of the band's two ends: a small tuberosity does not give way to the plateau's anterior rim."""
    v = frame.to_bone(bone.work.vertices)
    length = frame.mechanical_length_mm
    (lo, hi), end = settings.tuberosity_band, settings.tuberosity_band_end
    band = v[(v[:, 2] > lo * length) & (v[:, 2] < hi * length) & (v[:, 1] > np.abs(v[:, 0]))]
    low, high = band[band[:, 2] < (lo + end) * length], band[band[:, 2] > (hi - end) * length]
    if not len(low) or not len(high):
        raise FitError("no anterior surface at the tibial tuberosity's level")
    a, b = low[np.argmax(low[:, 1])], high[np.argmax(high[:, 1])]
    in_front = band[:, 1] - (a[1] + (band[:, 2] - a[2]) * (b[1] - a[1]) / (b[2] - a[2]))
    return band[np.argmax(in_front)]


def torsion_deg(plateau: np.ndarray, notch_x: float, malleolus: np.ndarray) -> float:
    """Tibial torsion (degrees, external positive) in bone coordinates (x lateral, y anterior, plafond
    centre at 0): from the posterior condylar line of the plateau section, a (p, 2) loop (its convex hull's
    edge behind ``notch_x``), to the line from the medial malleolus's centre ``malleolus`` (2,) to the
    plafond centre."""
    a, b = hull_edge_across(plateau, 0, notch_x, -1.0)
    proximal = (b - a) * np.sign(b[0] - a[0])
    distal = -np.asarray(malleolus, dtype=np.float64)
    # external torsion turns the distal axis clockwise seen from above (lateral towards posterior)
    turn = np.degrees(np.arctan2(proximal[1], proximal[0]) - np.arctan2(distal[1], distal[0]))
    return float((turn + 180.0) % 360.0 - 180.0)


def _outline(v: np.ndarray, faces: np.ndarray, height: float, where: str) -> np.ndarray:
    """(p, 2) x, y of the largest loop of the transverse section ``height`` mm above the plafond centre."""
    loops = section_mesh(v, faces, np.array([0.0, 0.0, height]), np.array([0.0, 0.0, 1.0])).loops()
    if not loops:
        raise FitError(f"no transverse section through {where} ({height:.1f} mm above the plafond centre)")
    return loops[0][:, :2]


def _chord(loop: np.ndarray, axis: int, value: float, where: str) -> tuple[float, float]:
    """Lowest and highest crossing of a loop with the line ``loop[:, axis] == value`` (mm)."""
    hits = line_crossings(loop, axis, value)
    if len(hits) < 2:
        raise FitError(f"the section line through {where} misses the bone")
    return float(hits[0]), float(hits[-1])


def _posterior_slope(v, faces, x: float, chord: tuple[float, float], length: float, window: float) -> float:
    """Posterior slope (degrees) of the plateau in the sagittal section at ``x`` (mm), over the chord's y range."""
    section = section_mesh(v, faces, np.array([x, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    pts = section.segments[:, 0, 1:]  # (y, z)
    top = pts[(pts[:, 1] > length - window) & (pts[:, 0] >= chord[0]) & (pts[:, 0] <= chord[1])]
    if len(top) < 3:
        raise FitError(f"no plateau surface in the sagittal section {x:.1f} mm lateral of the axis")
    posterior, anterior = sorted(hull_edge_across(top, 0, 0.5 * (chord[0] + chord[1]), 1.0), key=lambda p: p[0])
    return float(np.degrees(np.arctan2(anterior[1] - posterior[1], anterior[0] - posterior[0])))


def _articular_extent(v, faces, along: np.ndarray, settings: MorphometrySettings) -> float:
    """Extent (mm) along the horizontal unit vector ``along`` of the distally facing profile, within the band
    about the plafond level, of the vertical section through the plafond centre that contains ``along``."""
    normal = np.cross(along, [0.0, 0.0, 1.0])
    segments = section_mesh(v, faces, np.zeros(3), normal).segments
    d = segments[:, 1] - segments[:, 0]
    # the outward normal of a segment of a loop counter-clockwise about ``normal`` is d x normal
    outward = np.cross(d, normal)
    outward /= np.maximum(np.linalg.norm(outward, axis=1), 1e-300)[:, None]
    mid = segments.mean(axis=1)
    facing = (outward[:, 2] < -np.cos(np.radians(settings.plafond_facing_deg))) & (
        np.abs(mid[:, 2]) < settings.plafond_band_mm)
    if not facing.any():
        raise FitError("no distal articular surface at the plafond centre's level")
    ends = segments[facing] @ along
    return float(ends.max() - ends.min())
