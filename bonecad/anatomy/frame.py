"""The tibia's referential geometric entities (DESIGN.md step 2).

Mechanical axis from the plafond centre to the plateau centre; L-M and A-P
planes through it; local proximal axis; region boundaries; side; and the
canonical bone frame (origin at the plafond centre, x lateral, y anterior,
z proximal). For a left tibia that frame is the mirror image of a right
one's (its axes are left-handed in scanner space), so in bone coordinates
every tibia looks like a right one and later stages need no side cases.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bonecad.errors import FitError, InputError
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.mesh.sampling import triangle_areas
from bonecad.settings import AnatomySettings, UnitsSettings
from bonecad.mesh.sections import plane_basis, section_mesh, section_stack
from bonecad.anatomy.ellipse import fit_ellipse
from bonecad.anatomy.landmarks import FemurLandmarks

# Cut ends: the share of an end's section area covered by faces within this
# angle of the axis that makes the end a flat saw cut rather than a joint.
_FLAT_CUT_DEG = 3.0
_FLAT_CUT_SHARE = 0.5
_CUT_PLANE_BAND_MM = 0.25


@dataclass(frozen=True)
class PlateauEllipse:
    """The proximal articular outline fitted by an ellipse, in scanner coordinates (mm)."""

    centre: np.ndarray  # (3,)
    semi_axes_mm: np.ndarray  # (2,) major, minor
    major_direction: np.ndarray  # (3,) unit, perpendicular to the mechanical axis
    rms_residual_mm: float
    level_mm: float  # height of the fitted section above the plafond centre


@dataclass(frozen=True)
class AnatomicalFrame:
    """Reference entities of one tibia, all in the input's (scanner) coordinates, mm.

    ``axes`` rows are the unit lateral (x), anterior (y) and proximal (z)
    directions; ``origin`` is the plafond centre. ``to_bone``/``to_scanner``
    map points between scanner and bone coordinates.
    """

    side: str  # "left" | "right"
    origin: np.ndarray  # (3,)
    axes: np.ndarray  # (3, 3) rows: lateral, anterior, proximal
    plateau_centre: np.ndarray  # (3,)
    plafond_centre: np.ndarray  # (3,)
    plateau: PlateauEllipse
    mechanical_length_mm: float
    distal_apex: np.ndarray  # (3,) where the mechanical axis leaves the bone distally
    proximal_apex: np.ndarray  # (3,) where it leaves the bone proximally
    local_proximal_axis: np.ndarray  # (2, 3) start (plateau centre) and end point
    distal_boundary_mm: float  # height of the distal/shaft boundary above the origin
    proximal_boundary_mm: float  # height of the shaft/proximal boundary above the origin
    bone_extent_mm: np.ndarray  # (2,) lowest and highest height of the bone along z
    bone: str = "tibia"  # the bone profile ("tibia" | "femur")
    # a femur's own landmarks; its frame reuses the tibia's fields: plafond_centre and origin are the
    # knee centre, plateau_centre the head centre, plateau the condyles' widest section
    femur: FemurLandmarks | None = None

    @property
    def lateral(self) -> np.ndarray:
        """Unit vector towards lateral (the bone frame's x)."""
        return self.axes[0]

    @property
    def anterior(self) -> np.ndarray:
        """Unit vector towards anterior (y)."""
        return self.axes[1]

    @property
    def proximal(self) -> np.ndarray:
        """Unit vector towards proximal along the mechanical axis (z)."""
        return self.axes[2]

    @property
    def lm_plane_normal(self) -> np.ndarray:
        """Normal of the L-M plane (contains the axis, splits lateral from medial)."""
        return self.axes[0]

    @property
    def ap_plane_normal(self) -> np.ndarray:
        """Normal of the A-P plane (contains the axis, perpendicular to the L-M plane)."""
        return self.axes[1]

    def to_bone(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) scanner points -> bone coordinates (x lateral, y anterior, z proximal), mm."""
        return (np.asarray(points, dtype=np.float64) - self.origin) @ self.axes.T

    def to_scanner(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) bone coordinates -> scanner points, mm."""
        return np.asarray(points, dtype=np.float64) @ self.axes + self.origin

    @property
    def mirrored(self) -> bool:
        """True when bone coordinates are a mirror image of scanner space (a left tibia)."""
        return bool(np.linalg.det(self.axes) < 0)

    def as_dict(self) -> dict:
        """JSON-ready description, every entity in scanner coordinates (mm)."""
        tibia = self._tibia_dict()
        if self.femur is None:
            return tibia
        axis = tibia.pop("mechanical_axis")
        axis["start_knee_centre"] = axis.pop("start_plafond_centre")
        axis["end_head_centre"] = axis.pop("end_plateau_centre")
        direction = self.plateau_centre - self.plafond_centre
        axis["direction"] = np.round(direction / np.linalg.norm(direction), 6).tolist()
        tibia["bone_frame"]["proximal_is"] = "the anatomical (shaft) axis"
        condyles = tibia.pop("plateau_ellipse")
        return {"bone": self.bone, **tibia, "mechanical_axis": axis, "condyle_ellipse": condyles,
                **self.femur.as_dict()}

    def _tibia_dict(self) -> dict:
        r = lambda a: np.round(np.asarray(a, dtype=float), 6).tolist()  # noqa: E731
        return {
            "side": self.side,
            "units": "mm",
            "coordinates": "input (scanner) coordinates",
            "bone_frame": {
                "origin": r(self.origin),
                "lateral": r(self.axes[0]),
                "anterior": r(self.axes[1]),
                "proximal": r(self.axes[2]),
                "mirrored": self.mirrored,
            },
            "mechanical_axis": {
                "start_plafond_centre": r(self.plafond_centre),
                "end_plateau_centre": r(self.plateau_centre),
                "direction": r(self.axes[2]),
                "length_mm": round(self.mechanical_length_mm, 3),
            },
            "lm_plane": {"point": r(self.origin), "normal": r(self.lm_plane_normal)},
            "ap_plane": {"point": r(self.origin), "normal": r(self.ap_plane_normal)},
            "plateau_ellipse": {
                "centre": r(self.plateau.centre),
                "semi_axes_mm": r(self.plateau.semi_axes_mm),
                "major_direction": r(self.plateau.major_direction),
                "rms_residual_mm": round(self.plateau.rms_residual_mm, 4),
                "level_mm": round(self.plateau.level_mm, 3),
            },
            "apices": {"distal": r(self.distal_apex), "proximal": r(self.proximal_apex)},
            "local_proximal_axis": {"start": r(self.local_proximal_axis[0]), "end": r(self.local_proximal_axis[1])},
            "regions_mm_above_origin": {
                "distal": [round(float(self.bone_extent_mm[0]), 3), round(self.distal_boundary_mm, 3)],
                "shaft": [round(self.distal_boundary_mm, 3), round(self.proximal_boundary_mm, 3)],
                "proximal": [round(self.proximal_boundary_mm, 3), round(float(self.bone_extent_mm[1]), 3)],
            },
        }


def _area_weighted_axis(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid and principal direction of the surface (area-weighted triangle centroids)."""
    tri = vertices[faces]
    area = triangle_areas(vertices, faces)
    centres = tri.mean(axis=1)
    centre = (centres * area[:, None]).sum(axis=0) / area.sum()
    d = centres - centre
    cov = (d * area[:, None]).T @ d
    _, vecs = np.linalg.eigh(cov)
    return centre, vecs[:, -1]


def _unit_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    return n / np.maximum(norm, 1e-300)[:, None], 0.5 * norm


def _check_ends_whole(bone: BoneMesh, centre: np.ndarray, axis: np.ndarray, heights: np.ndarray,
                      lo: float, hi: float) -> None:
    """InputError when an end of the bone is a flat cut (a partial bone)."""
    normals, areas = _unit_normals(bone.vertices, bone.faces)
    face_h = heights[bone.faces].mean(axis=1)
    cos_flat = np.cos(np.radians(_FLAT_CUT_DEG))
    reach = 0.02 * (hi - lo)
    missing = []
    for name, sign, level in (("low", -1.0, lo), ("high", 1.0, hi)):
        candidates = (np.abs(face_h - level) < reach) & (normals @ (sign * axis) > cos_flat)
        if not candidates.any():
            continue
        # A cut is one plane (voxel staircases have many small terraces): keep
        # the faces on the plane of the area-weighted median offset.
        mean_normal = (normals[candidates] * areas[candidates, None]).sum(axis=0)
        mean_normal /= np.linalg.norm(mean_normal)
        centres = bone.vertices[bone.faces[candidates]].mean(axis=1)
        offsets = centres @ mean_normal
        order = np.argsort(offsets)
        cum = np.cumsum(areas[candidates][order])
        median = offsets[order][np.searchsorted(cum, 0.5 * cum[-1])]
        cut_area = float(areas[candidates][np.abs(offsets - median) < _CUT_PLANE_BAND_MM].sum())
        inner = level - sign * reach
        section = section_mesh(bone.vertices, bone.faces, centre + inner * axis, axis)
        if section.area > 0 and cut_area > _FLAT_CUT_SHARE * section.area:
            missing.append((name, cut_area))
    if missing:
        raise InputError(
            f"only part of a tibia: {_missing_end_description(bone, centre, axis, lo, hi, missing)}; bonecad "
            "needs the whole bone, from the tibial plateau (proximal articular surface) to the plafond and "
            "medial malleolus (distal)",
            bone.source or None,
        )


def _missing_end_description(bone, centre, axis, lo, hi, missing) -> str:
    """Name the cut end(s): an intact plateau's section is ~8x the narrowest shaft section, a plafond's ~3x."""
    if len(missing) == 2:
        return "both ends are flat cuts (" + ", ".join(f"{a:.0f} mm^2" for _, a in missing) + ")"
    name, cut_area = missing[0]
    length = hi - lo
    areas, _ = section_stack(bone.vertices, bone.faces, centre, axis, np.linspace(lo, hi, 40)[1:-1])
    intact = areas[:12] if name == "high" else areas[-12:]
    intact_is_plateau = intact.max() > 5.0 * areas[12:-12].min()
    cut, kept = ("distal", "proximal") if intact_is_plateau else ("proximal", "distal")
    return (
        f"the {cut} end is missing (the mesh ends in a flat cut of {cut_area:.0f} mm^2; "
        f"{length:.0f} mm of bone from the {kept} end are present)"
    )


def anatomical_frame(
    bone: BoneMesh,
    *,
    settings: AnatomySettings,
    plausible: UnitsSettings,
) -> AnatomicalFrame:
    """Find the tibia's frame from its anatomy (never from file names or scanner axes).

    Region boundaries are heights above the plafond centre (mm): the settings'
    when given (non-zero), else where the metaphyses flare (see ``_region_boundaries``).
    plausible : the whole tibia's length range (mm).
    Raises InputError, naming the file, when the bone lacks what every tibia has (a malleolus, a tuberosity,
    flaring ends, an articular surface at each end).
    """
    try:
        return _frame(bone, settings=settings, plausible=plausible)
    except InputError as exc:
        if exc.path is not None or not bone.source:
            raise
        raise InputError(exc.problem, bone.source) from exc


def _frame(bone: BoneMesh, *, settings: AnatomySettings, plausible: UnitsSettings) -> AnatomicalFrame:
    """``anatomical_frame``'s work (its InputErrors may not name the file)."""
    anat = settings
    bone = bone.work  # the shape, in as many triangles as the tolerance needs (``BoneMesh.working``)
    vertices, faces = bone.vertices, bone.faces
    centre, axis = _area_weighted_axis(vertices, faces)
    heights = (vertices - centre) @ axis
    lo, hi = float(heights.min()), float(heights.max())
    length = hi - lo
    lo_range, hi_range = plausible.tibia_length_mm
    _check_ends_whole(bone, centre, axis, heights, lo, hi)
    if not lo_range <= length <= hi_range:
        raise InputError(
            f"the bone is {length:.1f} mm long; a whole tibia is {lo_range:.0f}-{hi_range:.0f} mm "
            "(a partial bone, another bone, or a mesh in other units: see --units)",
            bone.source or None,
        )

    # Proximal end: the wider end (the plateau's section is about twice the plafond's).
    end_levels = np.linspace(0.02, 0.12, 6) * length
    low_areas, _ = section_stack(vertices, faces, centre, axis, lo + end_levels)
    high_areas, _ = section_stack(vertices, faces, centre, axis, hi - end_levels)
    if high_areas.max() < low_areas.max():
        axis = -axis
        heights = -heights
        lo, hi = -hi, -lo

    z = axis
    for _ in range(3):  # refine: plateau and plafond are sought perpendicular to the current axis
        plateau = _plateau(vertices, faces, centre, z, heights, hi, length, anat)
        plafond_centre = _plafond_centre(vertices, faces, centre, z, heights, lo, length, anat.plafond_search_share)
        plateau_centre = plateau.centre
        new_z = plateau_centre - plafond_centre
        new_z /= np.linalg.norm(new_z)
        converged = np.degrees(np.arccos(np.clip(new_z @ z, -1, 1))) < 0.01
        z = new_z
        heights = (vertices - centre) @ z
        lo, hi = float(heights.min()), float(heights.max())
        if converged:
            break

    mech_length = float(np.linalg.norm(plateau_centre - plafond_centre))
    rel = vertices - plafond_centre
    h = rel @ z
    anterior = _anterior_direction(vertices, faces, plafond_centre, z, mech_length)
    medial_hint = _medial_direction(vertices, plafond_centre, z, h, anterior)
    right_handed_lateral = np.cross(anterior, z)
    side = "right" if medial_hint @ right_handed_lateral < 0 else "left"
    lateral = right_handed_lateral if side == "right" else -right_handed_lateral
    axes = np.vstack([lateral, anterior, z])
    plateau = PlateauEllipse(
        centre=plateau.centre,
        semi_axes_mm=plateau.semi_axes_mm,
        major_direction=plateau.major_direction,
        rms_residual_mm=plateau.rms_residual_mm,
        level_mm=float((plateau.centre - plafond_centre) @ z),
    )

    if settings.distal_boundary_mm and settings.proximal_boundary_mm:
        distal_b, proximal_b = settings.distal_boundary_mm, settings.proximal_boundary_mm
    else:
        default_distal, default_proximal = _region_boundaries(vertices, faces, plafond_centre, z, mech_length,
                                                              anat)
        distal_b = settings.distal_boundary_mm or default_distal
        proximal_b = settings.proximal_boundary_mm or default_proximal
    h_lo, h_hi = float(h.min()), float(h.max())
    if not h_lo < distal_b < proximal_b < h_hi:
        raise InputError(
            f"region boundaries must satisfy {h_lo:.1f} < distal ({distal_b:.1f}) < proximal "
            f"({proximal_b:.1f}) < {h_hi:.1f} mm above the plafond centre"
        )
    lowest_proximal = section_mesh(vertices, faces, plafond_centre + proximal_b * z, z)
    local_axis = np.vstack([plateau_centre, lowest_proximal.centroid])
    distal_apex, proximal_apex = _axis_exits(vertices, faces, plafond_centre, z)
    return AnatomicalFrame(
        side=side,
        origin=plafond_centre,
        axes=axes,
        plateau_centre=plateau_centre,
        plafond_centre=plafond_centre,
        plateau=plateau,
        mechanical_length_mm=mech_length,
        distal_apex=distal_apex,
        proximal_apex=proximal_apex,
        local_proximal_axis=local_axis,
        distal_boundary_mm=distal_b,
        proximal_boundary_mm=proximal_b,
        bone_extent_mm=np.array([h_lo, h_hi]),
    )


def _plateau(vertices, faces, centre, z, heights, hi, length, anat) -> PlateauEllipse:
    """Ellipse fitted to the widest section just below the proximal articular surface."""
    depth = anat.plateau_search_share * length
    levels = hi - np.linspace(0.1, 1.0, 10) * depth
    areas, _ = section_stack(vertices, faces, centre, z, levels)
    best = int(np.argmax(areas))
    section = section_mesh(vertices, faces, centre + levels[best] * z, z)
    loops = section.loops()
    if not loops:
        raise FitError("no section through the tibial plateau")
    outline = loops[0]
    u, v = plane_basis(z)
    origin = centre + levels[best] * z
    pts = np.column_stack([(outline - origin) @ u, (outline - origin) @ v])
    ellipse = fit_ellipse(pts)
    centre_on_plane = origin + ellipse.centre[0] * u + ellipse.centre[1] * v
    major = ellipse.major_direction[0] * u + ellipse.major_direction[1] * v
    # The plateau centre lies on the articular surface above the ellipse centre
    # (the intercondylar region between the tibial spines).
    top = _ray_hits(vertices, faces, centre_on_plane, z)
    point = centre_on_plane + (top.max() if len(top) else 0.0) * z
    return PlateauEllipse(point, ellipse.semi_axes, major, ellipse.rms_residual_mm, 0.0)


def _plafond_centre(vertices, faces, centre, z, heights, lo, length, search_share: float) -> np.ndarray:
    """Centroid of distal cross-sections just above the distal articular surface (searched within
    ``search_share`` of the length from the distal end)."""
    normals, areas = _unit_normals(vertices, faces)
    face_h = heights[faces].mean(axis=1)
    search = lo + search_share * length
    facing = (face_h < search) & (normals @ -z > 0.7)
    if areas[facing].sum() <= 0:
        raise InputError("the tibia's distal end shows no articular surface (no distal-facing faces near it): the "
                         "end is cut off or another bone is fused to it; give the whole tibia, separated from its "
                         "talus")
    # Area-weighted median height of the distal-facing surface = the plafond level.
    order = np.argsort(face_h[facing])
    cum = np.cumsum(areas[facing][order])
    level = face_h[facing][order][np.searchsorted(cum, 0.5 * cum[-1])]
    offsets = np.array([2.0, 4.0, 6.0, 8.0, 10.0])
    _, centroids = section_stack(vertices, faces, centre, z, level + offsets)
    ok = np.isfinite(centroids).all(axis=1)
    xy = centroids[ok].mean(axis=0)
    return xy + (level - (xy - centre) @ z) * z


def _anterior_direction(vertices, faces, plafond_centre, z, mech_length) -> np.ndarray:
    """Unit anterior direction: the proximal shaft and tuberosity lie anterior to the mechanical axis.

    The mechanical axis runs near the posterior cortex in the proximal third
    (the plateau overhangs posteriorly, the tuberosity juts anteriorly), so
    the section centroids there, measured from the axis, point anterior.
    """
    levels = mech_length * np.linspace(0.72, 0.88, 5)
    _, centroids = section_stack(vertices, faces, plafond_centre, z, levels)
    offsets = centroids - (plafond_centre + np.outer(levels, z))
    offsets -= np.outer(offsets @ z, z)
    direction = offsets.mean(axis=0)
    norm = np.linalg.norm(direction)
    if norm < 1.0:
        raise InputError(f"the tibia's front cannot be told: its proximal sections lie {norm:.2f} mm from the axis "
                         "(a tibia's tuberosity puts them several mm in front); the body may not be a tibia, or "
                         "another bone is fused to it; give the whole tibia alone (or --bone femur for a femur)")
    return direction / norm


def _medial_direction(vertices, plafond_centre, z, h, anterior) -> np.ndarray:
    """Unit vector towards the medial malleolus, the lowest part of the tibia, seen from the axis."""
    low = h < h.min() + 3.0
    tip = vertices[low].mean(axis=0)
    d = tip - plafond_centre
    d -= (d @ z) * z + (d @ anterior) * anterior
    norm = np.linalg.norm(d)
    if norm < 2.0:
        raise InputError(f"the tibia's side cannot be told: the lowest 3 mm of the bone lie {norm:.1f} mm from the "
                         "axis, where a tibia's medial malleolus stands out (2 mm or more); its distal end is cut "
                         "off or another bone (the talus) is fused to it; give the whole tibia, separated from its "
                         "talus")
    return d / norm


def _region_boundaries(vertices, faces, origin, z, mech_length, anat) -> tuple[float, float]:
    """Heights (mm above the plafond centre) where the distal and proximal metaphyses flare.

    Walking from the narrowest shaft section towards each end, a boundary is
    the last level whose section area stays below the configured multiple of
    the narrowest one (``distal_flare_ratio``, ``proximal_flare_ratio``).
    """
    levels = np.linspace(0.05, 0.95, 91) * mech_length
    areas, _ = section_stack(vertices, faces, origin, z, levels)
    shaft = (levels > 0.3 * mech_length) & (levels < 0.7 * mech_length)
    mid = int(np.argmin(np.where(shaft, areas, np.inf)))
    narrowest = areas[mid]
    wide_below = np.flatnonzero(areas[:mid] > anat.distal_flare_ratio * narrowest)
    wide_above = np.flatnonzero(areas[mid:] > anat.proximal_flare_ratio * narrowest)
    if len(wide_below) == 0 or len(wide_above) == 0:
        raise InputError("the bone's ends do not flare as a tibia's metaphyses do: cannot place the region "
                         "boundaries; check the input is a whole tibia, or give both boundaries (--distal-boundary and "
                         "--proximal-boundary)")
    return float(levels[wide_below[-1] + 1]), float(levels[mid + wide_above[0] - 1])


def _ray_hits(vertices, faces, origin, direction) -> np.ndarray:
    """Signed distances along the line origin + t*direction where it crosses the mesh (mm)."""
    tri = vertices[faces]
    u, v = plane_basis(direction)
    p2 = np.stack([(tri - origin) @ u, (tri - origin) @ v], axis=-1)  # (m, 3, 2)
    a, b, c = p2[:, 0], p2[:, 1], p2[:, 2]
    cross = lambda p, q: p[:, 0] * q[:, 1] - p[:, 1] * q[:, 0]  # noqa: E731
    w0 = cross(b, c)
    w1 = cross(c, a)
    w2 = cross(a, b)
    total = w0 + w1 + w2
    inside = (np.sign(w0) == np.sign(total)) & (np.sign(w1) == np.sign(total)) & (np.sign(w2) == np.sign(total))
    inside &= np.abs(total) > 1e-12
    if not inside.any():
        return np.zeros(0)
    bary = np.stack([w0[inside], w1[inside], w2[inside]], axis=1) / total[inside, None]
    t = (bary[:, :, None] * tri[inside]).sum(axis=1) @ direction - origin @ direction
    return np.sort(t)


def _axis_exits(vertices, faces, origin, z) -> tuple[np.ndarray, np.ndarray]:
    """Points where the mechanical axis leaves the bone, distally and proximally."""
    hits = _ray_hits(vertices, faces, origin, z)
    if len(hits) < 2:
        raise InputError("the line from the plafond's centre to the plateau's does not pass through the bone: "
                         "the shape is not a tibia's (a bent, broken or fused bone?); give the whole tibia alone")
    return origin + hits[0] * z, origin + hits[-1] * z
