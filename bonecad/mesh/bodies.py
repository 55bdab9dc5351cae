"""The bodies of a leg mesh by anatomy: which is the tibia, what the others are, and fused bones.

All lengths in mm, volumes in mm^3; every threshold is a ``MeshSettings``
field (``data/defaults.toml`` [mesh] gives the measurements behind each).
Roles: tibia, fibula, femur, patella, talus, foot bone, broken piece, fragment.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bonecad.errors import InputError
from bonecad.mesh.sections import LevelSections, plane_basis, section_stack
from bonecad.settings import MeshSettings


@dataclass(frozen=True)
class BodyShape:
    """What the rules read of one body: volume (mm^3), principal axis, length along it and largest width
    across it (mm), centroid (mm)."""

    volume: float
    axis: np.ndarray
    length: float
    width: float
    centroid: np.ndarray

    @property
    def slenderness(self) -> float:
        return self.length / max(self.width, 1e-9)


def body_shape(vertices: np.ndarray, volume: float, centroid: np.ndarray) -> BodyShape:
    """Principal axis, length and largest width (mm) of one body's vertices."""
    centred = vertices - vertices.mean(axis=0)
    _, _, vt = np.linalg.svd(centred[:: max(1, len(vertices) // 20000)], full_matrices=False)
    along = centred @ vt[0]
    across = centred @ vt[1:].T
    width = float((across.max(axis=0) - across.min(axis=0)).max()) if len(vertices) else 0.0
    return BodyShape(abs(volume), vt[0], float(np.ptp(along)), width, np.asarray(centroid, dtype=np.float64))


def choose_tibia(shapes: list[BodyShape], settings: MeshSettings, length_range: tuple[float, float]) -> int:
    """Index of the tibia: the largest long, not thin body of a tibia's length that is not a femur (the
    longer of two long bones meeting end to end); the largest body when none qualifies."""
    lo, hi = length_range
    candidates = [
        i for i, s in enumerate(shapes)
        if lo <= s.length <= hi and settings.long_body_slenderness <= s.slenderness < settings.thin_body_slenderness
    ]
    femurs = set()
    for i in candidates:
        for j in candidates:
            a, b = shapes[i], shapes[j]
            beyond = abs((b.centroid - a.centroid) @ a.axis) > 0.5 * a.length  # end to end, not side by side
            if i != j and beyond and a.length > b.length:
                femurs.add(i)
    left = [i for i in candidates if i not in femurs]
    if not left:
        return int(np.argmax([s.volume for s in shapes]))
    return max(left, key=lambda i: shapes[i].volume)


def proximal_direction(vertices: np.ndarray, faces: np.ndarray, centre: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """``axis`` or its opposite, pointing to the wider end (the plateau's sections are about twice the plafond's)."""
    heights = (vertices - centre) @ axis
    lo, hi = float(heights.min()), float(heights.max())
    levels = np.linspace(0.02, 0.12, 6) * (hi - lo)
    low, _ = section_stack(vertices, faces, centre, axis, lo + levels)
    high, _ = section_stack(vertices, faces, centre, axis, hi - levels)
    return axis if high.max() >= low.max() else -axis


def body_roles(shapes: list[BodyShape], t: int, up: np.ndarray, settings: MeshSettings) -> list[str]:
    """The role of every body (see the module docstring), from its place relative to the tibia ``shapes[t]``.

    up : unit vector along the tibia's axis towards its plateau (``proximal_direction``)."""
    tibia = shapes[t]
    half = 0.5 * tibia.length
    end_zone = half - settings.end_zone_share * tibia.length  # centroids further out than this: knee or ankle
    roles = ["fragment"] * len(shapes)
    roles[t] = "tibia"
    ankle: list[int] = []
    for i, s in enumerate(shapes):
        if i == t or s.volume < settings.fragment_volume_share * tibia.volume:
            continue
        offset = s.centroid - tibia.centroid
        height = float(offset @ up)
        off_axis = float(np.linalg.norm(offset - height * up))
        parallel = abs(float(s.axis @ up)) > 0.9
        if parallel and abs(height) < 0.5 * half and s.length > 0.5 * tibia.length:
            roles[i] = "fibula"
        elif height > end_zone:
            long_bone = s.slenderness >= settings.long_body_slenderness
            if not long_bone and off_axis >= settings.patella_min_offset_mm:
                roles[i] = "patella"
            elif long_bone or s.volume >= settings.broken_piece_volume_share * tibia.volume:
                roles[i] = "femur"  # long, or as large as a distal femur
            else:
                roles[i] = "broken piece"  # small, on the axis beyond the plateau: part of the tibia
        elif (parallel and s.volume >= settings.broken_piece_volume_share * tibia.volume
              and s.slenderness >= settings.long_body_slenderness):
            roles[i] = "broken piece"
        elif height < -end_zone:
            ankle.append(i)
        elif s.volume >= settings.broken_piece_volume_share * tibia.volume:
            roles[i] = "broken piece"
    if ankle:
        # the talus sits on the plafond: the ankle body nearest the tibia's distal end; the rest is the foot
        nearest = min(ankle, key=lambda i: abs(float((shapes[i].centroid - tibia.centroid) @ up) + half))
        for i in ankle:
            roles[i] = "talus" if i == nearest else "foot bone"
    return roles


def _loop_areas(section) -> np.ndarray:
    """Signed areas (mm^2) of a section's closed loops, largest first (holes negative)."""
    u, v = plane_basis(section.normal)
    areas = []
    for loop in section.loops():
        xy = np.stack([(loop - section.origin) @ u, (loop - section.origin) @ v], axis=1)
        nxt = np.roll(xy, -1, axis=0)
        areas.append(0.5 * float((xy[:, 0] * nxt[:, 1] - nxt[:, 0] * xy[:, 1]).sum()))
    return np.sort(np.array(areas))[::-1]


def neck_index(areas: np.ndarray, ratio: float) -> int | None:
    """Index of the neck in section areas (mm^2) walking from a bone's end inwards: the smallest area with
    at least ``ratio`` times it both between it and the end and beyond it (a second bone joined to the end
    through a narrow joint); None when the areas show no neck."""
    outer_peak = np.maximum.accumulate(areas)  # largest area between the end and each depth
    inner_peak = np.maximum.accumulate(areas[::-1])[::-1]  # ... between each depth and the zone's inner edge
    neck = (outer_peak >= ratio * areas) & (inner_peak >= ratio * areas) & (areas > 0)
    if not neck.any():
        return None
    return int(np.argmin(np.where(neck, areas, np.inf)))


def check_not_fused(vertices: np.ndarray, faces: np.ndarray, settings: MeshSettings, longest_mm: float,
                    source: Path | None) -> None:
    """InputError naming the neighbour when the kept body holds a second bone: a femur (longer than any
    single bone, ``longest_mm``: the longer of the tibia's and the femur's plausible lengths; a long femur
    is no fused tibia), a fibula (a second section loop along much of its length) or a bone at one end (a
    neck near the end)."""
    centre = vertices.mean(axis=0)
    shape = body_shape(vertices, 0.0, centre)
    advice = "; separate them in the segmentation (bonecad models one bone)"
    if shape.length > longest_mm:
        raise InputError(
            f"one body {shape.length:.0f} mm long, longer than any tibia or femur (at most {longest_mm:.0f} mm): "
            f"the tibia seems fused to its femur at the knee{advice}",
            source,
        )
    up = proximal_direction(vertices, faces, centre, shape.axis)
    heights = (vertices - centre) @ up
    bottom, top = float(heights.min()), float(heights.max())
    length = top - bottom

    # the fibula beside the tibia: a second outer loop in the sections across the axis
    levels = np.linspace(bottom, top, 92)[1:-1]
    stack = LevelSections(vertices, faces, centre, up)
    second = np.array([
        (areas[1] if len(areas) > 1 else 0.0) for areas in (_loop_areas(stack.at(float(h))) for h in levels)
    ])
    beside = levels[second >= settings.fused_second_loop_mm2]
    # the sections showing it must cover the share themselves: a malleolus cut off by the plafond's curve near
    # one end and the spines of the plateau near the other span the length but cover little of it
    if len(beside) >= settings.fused_loop_stretch_share * len(levels):
        a, b = beside.min() - bottom, beside.max() - bottom
        raise InputError(
            f"the tibia is fused to its fibula: sections across its axis show the fibula beside it from "
            f"{a:.0f} to {b:.0f} mm above the body's distal end (of {length:.0f} mm), joined to it at the ends "
            f"of that stretch (the tibiofibular joints, near {a:.0f} and {b:.0f} mm){advice}",
            source,
        )

    # a bone fused at an end: walking inwards from the end, the section areas fall to a neck and rise again
    step = 3.0
    depth = np.arange(1.0, settings.fused_neck_zone_share * length, step)
    for name, end, sign in (("distal", bottom, 1.0), ("proximal", top, -1.0)):
        areas, _ = section_stack(vertices, faces, centre, up, end + sign * depth)
        k = neck_index(areas, settings.fused_neck_ratio)
        if k is not None:
            outer_peak, inner_peak = areas[: k + 1].max(), areas[k:].max()
            bone = "talus at the ankle" if name == "distal" else "femur (or patella) at the knee"
            raise InputError(
                f"the tibia seems fused to its {bone}: a second bone hangs beyond its {name} end, joined to it "
                f"through a neck {depth[k]:.0f} mm from that end (section areas {outer_peak:.0f} -> "
                f"{areas[k]:.0f} -> {inner_peak:.0f} mm^2){advice}",
                source,
            )
