"""The femur's referential geometric entities (issue 22).

Femoral head (a sphere fitted by least squares to the surface found by a
Hough vote of the face normals at the narrow end), neck axis, knee centre
(between the condyles, just above the distal articular surface), posterior
condyle spheres, epicondyles and the transepicondylar axis, mechanical axis
(knee centre -> head centre), anatomical (shaft) axis, side, the raters' 22
landmarks (``anatomy.femur_points``: head, neck isthmus, trochanters, condyles,
epicondyles, notch) and the ISB femur frame (Wu et al. 2002). The bone frame the later stages use is the tibia's
convention: origin at the knee centre, z proximal along the mechanical axis,
y anterior, x lateral (mirrored for a left femur), so the contour and model
stages need no femur cases; the proximal end region's local axis runs from the
head centre to the centroid of the shaft below the lesser trochanter (the
curved centreline: notch, shaft, neck, head).
"""
from __future__ import annotations

import numpy as np

from bonecad.anatomy.ellipse import fit_ellipse
from bonecad.anatomy.femur_points import femur_points
from bonecad.anatomy.landmarks import FemurLandmarks, Sphere
from bonecad.anatomy.frame import (AnatomicalFrame, PlateauEllipse, _area_weighted_axis, _axis_exits,
                                   _plafond_centre, _region_boundaries, _unit_normals)
from bonecad.errors import FitError, InputError
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.mesh.sections import plane_basis, section_mesh, section_stack
from bonecad.settings import FemurSettings
from bonecad.splines.lsq import least_squares


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Least-squares sphere through (n, 3) points (algebraic fit, exact for points on a sphere):
    (centre, radius, RMS of the radial residuals), mm."""
    design = np.column_stack([2.0 * points, np.ones(len(points))])
    rhs = (points**2).sum(axis=1)
    sol = least_squares(design, rhs)
    centre = sol[:3]
    radius = float(np.sqrt(max(sol[3] + centre @ centre, 0.0)))
    rms = float(np.sqrt(np.mean((np.linalg.norm(points - centre, axis=1) - radius) ** 2)))
    return centre, radius, rms


def find_head(vertices: np.ndarray, faces: np.ndarray, zone: np.ndarray, settings: FemurSettings) -> Sphere | None:
    """The largest sphere-shaped surface among the faces of ``zone`` (a boolean mask): None when none
    covers ``settings.head_min_coverage`` of its sphere.

    Every face votes, for each radius of ``settings.head_radius_mm``, for the centre one radius inside
    it along its normal (area-weighted, in ``head_vote_bin_mm`` bins); the faces near the winning
    sphere are refitted by least squares until the inliers settle.
    """
    normals, areas = _unit_normals(vertices, faces)
    centres = vertices[faces].mean(axis=1)
    normals, areas, centres = normals[zone], areas[zone], centres[zone]
    if len(centres) < 20:
        return None
    lo, hi = settings.head_radius_mm
    radii = np.arange(lo, hi + 1e-9, settings.head_vote_bin_mm / 2)
    votes = centres[:, None, :] - radii[None, :, None] * normals[:, None, :]
    bins = np.floor(votes.reshape(-1, 3) / settings.head_vote_bin_mm).astype(np.int64)
    # one int64 key per bin, in the bins' lexicographic order (a sort of rows costs 15x a sort of keys)
    low = bins.min(axis=0)
    span = bins.max(axis=0) - low + 1
    keys, inverse = np.unique(np.ravel_multi_index((bins - low).T, span), return_inverse=True)
    tally = np.bincount(inverse, weights=np.repeat(areas, len(radii)), minlength=len(keys))
    best = int(np.argmax(tally))
    centre = (low + np.array(np.unravel_index(keys[best], span)) + 0.5) * settings.head_vote_bin_mm
    radius = float(np.median(np.linalg.norm(centres - centre, axis=1)[(inverse.ravel() == best).reshape(
        len(centres), len(radii)).any(axis=1)]))
    band = settings.head_inlier_mm
    inliers = np.zeros(len(centres), bool)
    for _ in range(20):
        rel = centres - centre
        dist = np.linalg.norm(rel, axis=1)
        new = (np.abs(dist - radius) < band) & (np.einsum("ij,ij->i", rel, normals) > 0.9 * dist)
        if new.sum() < 20:
            return None
        if np.array_equal(new, inliers):
            break
        inliers = new
        centre, radius, rms = fit_sphere(centres[inliers])
    coverage = float(areas[inliers].sum() / (4 * np.pi * radius**2))
    if coverage < settings.head_min_coverage or not lo <= radius <= hi:
        return None
    return Sphere(centre, radius, rms, coverage)


def _end_zone(vertices: np.ndarray, faces: np.ndarray, axis: np.ndarray, share: float, high: bool) -> np.ndarray:
    """Faces whose centres lie within ``share`` of the length from the low (or high) end along ``axis``."""
    h = vertices[faces].mean(axis=1) @ axis
    lo, hi = h.min(), h.max()
    reach = share * (hi - lo)
    return h > hi - reach if high else h < lo + reach


def wider_end_axis(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The surface's centroid, its principal axis pointing to the wider end (by section areas 2-12 %
    of the length in from each end) and its length along that axis (mm)."""
    centre, axis = _area_weighted_axis(vertices, faces)
    heights = (vertices - centre) @ axis
    lo, hi = float(heights.min()), float(heights.max())
    length = hi - lo
    end_levels = np.linspace(0.02, 0.12, 6) * length
    low_areas, _ = section_stack(vertices, faces, centre, axis, lo + end_levels)
    high_areas, _ = section_stack(vertices, faces, centre, axis, hi - end_levels)
    if high_areas.max() < low_areas.max():
        axis = -axis
    return centre, axis, length


def head_at_narrow_end(bone: BoneMesh, settings: FemurSettings) -> tuple[Sphere | None, np.ndarray, float]:
    """The femoral head at the narrower end of a bone (None when no sphere is there, or one on the long
    axis rather than off it on a neck), the unit axis towards the wider end and the bone's length (mm)."""
    work = bone.work
    centre, axis, length = wider_end_axis(work.vertices, work.faces)
    zone = _end_zone(work.vertices, work.faces, axis, settings.head_search_share, high=False)
    head = find_head(work.vertices, work.faces, zone, settings)
    if head is not None:
        rel = head.centre - centre
        if np.linalg.norm(rel - (rel @ axis) * axis) < settings.head_min_offset_mm:
            head = None  # a rounded end on the long axis, not a head on a neck
    return head, axis, length


def femur_frame(bone: BoneMesh, *, settings: FemurSettings) -> AnatomicalFrame:
    """The femur's frame and landmarks, from its anatomy (never from file names or scanner axes).

    The knee end is the wider end; the head is the sphere at the other. Region boundaries are heights
    above the knee centre (mm): the settings' when non-zero, else where the metaphyses flare.
    """
    head, to_knee, length = head_at_narrow_end(bone, settings)
    if head is None:
        raise InputError(f"no femoral head: no sphere of {settings.head_radius_mm[0]:.0f}-"
                         f"{settings.head_radius_mm[1]:.0f} mm radius at the narrow end of this "
                         f"{length:.0f} mm bone", bone.source or None)
    work = bone.work
    vertices, faces = work.vertices, work.faces
    z = -to_knee
    knee = np.zeros(3)
    for _ in range(4):  # the knee centre is sought perpendicular to the current mechanical axis
        heights = (vertices - head.centre) @ z
        lo = float(heights.min())
        knee = _plafond_centre(vertices, faces, head.centre, z, heights, lo, length, settings.knee_search_share)
        new_z = (head.centre - knee) / np.linalg.norm(head.centre - knee)
        done = np.degrees(np.arccos(np.clip(new_z @ z, -1, 1))) < 0.01
        z = new_z
        if done:
            break
    mech_length = float(np.linalg.norm(head.centre - knee))
    shaft_axis = _shaft_axis(vertices, faces, knee, z, mech_length)
    # the bone frame's z: the anatomical axis through the knee centre, which stays inside the distal
    # femur (the mechanical axis leaves the shaft a few centimetres above the knee)
    z = (shaft_axis[1] - shaft_axis[0]) / np.linalg.norm(shaft_axis[1] - shaft_axis[0])
    # ... and its origin on that axis at the knee centre's level: the axis leaves the bone at the roof of the
    # intercondylar notch (the intramedullary entry point), where the distal apex hole is
    origin = shaft_axis[0] + ((knee - shaft_axis[0]) @ z) * z
    h = (vertices - origin) @ z

    condyles = _widest_knee_section(vertices, faces, knee, z, settings)
    anterior = _anterior(vertices, faces, knee, z, condyles.major_direction, mech_length, shaft_axis)
    right = np.cross(anterior, z)
    # the head is medial of the shaft
    medial_hint = head.centre - shaft_axis[0] - ((head.centre - shaft_axis[0]) @ z) * z
    side = "right" if medial_hint @ right < 0 else "left"
    condyle_c, _ = _posterior_condyles(vertices, faces, knee, z, anterior, right if side == "right" else -right,
                                       settings)
    # refined: perpendicular to the posterior condylar axis (through the two condyles' sphere centres)
    across = (condyle_c[1] - condyle_c[0]) - ((condyle_c[1] - condyle_c[0]) @ z) * z
    refined = np.cross(z, across) / np.linalg.norm(across)
    anterior = refined * np.sign(refined @ anterior)
    right = np.cross(anterior, z)
    lateral = right if side == "right" else -right
    axes = np.vstack([lateral, anterior, z])
    condyle_c, condyle_r = _posterior_condyles(vertices, faces, knee, z, anterior, lateral, settings)
    neck_axis = _neck_axis(vertices, faces, head, shaft_axis, anterior)
    points = femur_points(vertices, faces, head=head, neck_axis=neck_axis, knee=knee, axes=axes,
                          shaft_axis=shaft_axis, condyle_centres=condyle_c, condyle_radii=condyle_r,
                          epicondyle_reach_mm=settings.epicondyle_reach_mm,
                          epicondyle_cap_mm=settings.epicondyle_cap_mm)
    epicondyles = np.vstack([points["MEC"], points["LEC"]])
    y_isb = head.centre - epicondyles.mean(axis=0)
    y_isb /= np.linalg.norm(y_isb)
    tea = epicondyles[1] - epicondyles[0]
    tea *= np.sign(tea @ right)
    z_isb = tea - (tea @ y_isb) * y_isb
    z_isb /= np.linalg.norm(z_isb)
    isb = np.vstack([np.cross(y_isb, z_isb), y_isb, z_isb])

    default_distal, default_proximal = _region_boundaries(vertices, faces, origin, z, mech_length, settings)
    distal_b = settings.distal_boundary_mm or default_distal
    proximal_b = settings.proximal_boundary_mm or default_proximal
    h_lo, h_hi = float(h.min()), float(h.max())
    if not h_lo < distal_b < proximal_b < h_hi:
        raise InputError(f"region boundaries must satisfy {h_lo:.1f} < distal ({distal_b:.1f}) < proximal "
                         f"({proximal_b:.1f}) < {h_hi:.1f} mm above the knee centre")
    below_trochanters = _shaft_loop_centroid(vertices, faces, origin + proximal_b * z, z)
    distal_apex, _ = _axis_exits(vertices, faces, origin, z)
    neck_up = (head.centre - below_trochanters) / np.linalg.norm(head.centre - below_trochanters)
    _, proximal_apex = _axis_exits(vertices, faces, below_trochanters, neck_up)
    landmarks = FemurLandmarks(head=head, neck_axis=neck_axis, knee_centre=knee, condyle_centres=condyle_c,
                               condyle_radii_mm=condyle_r, epicondyles=epicondyles, shaft_axis=shaft_axis,
                               isb_axes=isb, points=points)
    return AnatomicalFrame(
        side=side, origin=origin, axes=axes, plateau_centre=head.centre, plafond_centre=knee,
        plateau=replace_level(condyles, origin, z), mechanical_length_mm=mech_length,
        distal_apex=distal_apex, proximal_apex=proximal_apex,
        local_proximal_axis=np.vstack([head.centre, below_trochanters]),
        distal_boundary_mm=distal_b, proximal_boundary_mm=proximal_b, bone_extent_mm=np.array([h_lo, h_hi]),
        bone="femur", femur=landmarks,
    )


def replace_level(ellipse: PlateauEllipse, knee: np.ndarray, z: np.ndarray) -> PlateauEllipse:
    """The condyles' ellipse with its level above the knee centre (mm)."""
    return PlateauEllipse(ellipse.centre, ellipse.semi_axes_mm, ellipse.major_direction, ellipse.rms_residual_mm,
                          float((ellipse.centre - knee) @ z))


def _widest_knee_section(vertices, faces, knee, z, settings: FemurSettings) -> PlateauEllipse:
    """Ellipse fitted to the widest section (all its loops' points) within ``condyle_search_mm`` above the
    knee centre: its major axis is the medial-lateral direction."""
    levels = np.linspace(5.0, settings.condyle_search_mm, 12)
    areas, _ = section_stack(vertices, faces, knee, z, levels)
    level = levels[int(np.argmax(areas))]
    origin = knee + level * z
    section = section_mesh(vertices, faces, origin, z)
    loops = section.loops()
    if not loops:
        raise FitError("no section through the femoral condyles")
    outline = np.vstack(loops)
    u, v = plane_basis(z)
    ellipse = fit_ellipse(np.column_stack([(outline - origin) @ u, (outline - origin) @ v]))
    centre = origin + ellipse.centre[0] * u + ellipse.centre[1] * v
    major = ellipse.major_direction[0] * u + ellipse.major_direction[1] * v
    return PlateauEllipse(centre, ellipse.semi_axes, major, ellipse.rms_residual_mm, level)


def _shaft_axis(vertices, faces, knee, z, mech_length) -> np.ndarray:
    """The anatomical axis: a line through the section centroids of the middle of the shaft (30-70 % of
    the mechanical length), returned as its points at those two heights."""
    levels = np.linspace(0.3, 0.7, 9) * mech_length
    _, centroids = section_stack(vertices, faces, knee, z, levels)
    ok = np.isfinite(centroids).all(axis=1)
    mean = centroids[ok].mean(axis=0)
    _, _, vt = np.linalg.svd(centroids[ok] - mean)
    d = vt[0] * np.sign(vt[0] @ z)
    ends = ((knee + levels[[0, -1], None] * z) - mean) @ z / (d @ z)
    return mean + ends[:, None] * d


def _anterior(vertices, faces, knee, z, ml, mech_length, shaft_axis) -> np.ndarray:
    """Unit anterior direction: perpendicular to the axis and the condyles' medial-lateral direction,
    on the side away from the posterior condyles (they stand behind the distal shaft)."""
    ap = np.cross(z, ml)
    ap /= np.linalg.norm(ap)
    levels = np.linspace(0.02, 0.08, 4) * mech_length
    _, centroids = section_stack(vertices, faces, knee, z, levels)
    ok = np.isfinite(centroids).all(axis=1)
    a, b = shaft_axis
    d = (b - a) / np.linalg.norm(b - a)
    on_shaft = a + (((centroids[ok] - a) @ z) / (d @ z))[:, None] * d
    offset = float(np.mean((centroids[ok] - on_shaft) @ ap))
    if abs(offset) < 1.0:
        raise FitError(f"anterior direction is ill-defined (the condyles lie {offset:.2f} mm behind the shaft)")
    return -ap if offset > 0 else ap


def _posterior_condyles(vertices, faces, knee, z, anterior, lateral, settings: FemurSettings
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Spheres fitted to the posterior-facing surface of each condyle (rows medial, lateral): centres, radii."""
    normals, _ = _unit_normals(vertices, faces)
    centres = vertices[faces].mean(axis=1)
    rel = centres - knee
    h = rel @ z
    back = (h < settings.condyle_search_mm) & (normals @ -anterior > 0.5) & (rel @ anterior < 0)
    out_c, out_r = [], []
    for sign in (-1.0, 1.0):
        mask = back & (sign * (rel @ lateral) > 5.0)
        if mask.sum() < 20:
            raise FitError("too few posterior condyle faces for a sphere fit")
        c, r, _ = fit_sphere(centres[mask])
        out_c.append(c)
        out_r.append(r)
    return np.array(out_c), np.array(out_r)


def _neck_axis(vertices, faces, head: Sphere, shaft_axis: np.ndarray, anterior: np.ndarray) -> np.ndarray:
    """The neck axis: from the head centre to the centroid of the neck's smallest section 1.3-1.6 head radii
    from the centre, over planes whose normals lie within 60 degrees of the line from the head centre to
    the shaft axis and whose section is centred on the neck (a plane perpendicular to the neck cuts it
    smallest); ``anterior`` orients the planes' grid."""
    a, b = shaft_axis
    d = (b - a) / np.linalg.norm(b - a)
    foot = a + ((head.centre - a) @ d) * d
    towards = (foot - head.centre) / np.linalg.norm(foot - head.centre)
    # the planes' tilts turn about ``towards`` from the anterior direction, so that the axis found moves
    # with the bone (a basis from the scanner's axes gave a neck axis 0.2-0.8 mm apart on a moved femur)
    u = anterior - (anterior @ towards) * towards
    u /= np.linalg.norm(u)
    v = np.cross(towards, u)
    tilt = np.radians(np.arange(0.0, 61.0, 10.0))
    turn = np.radians(np.arange(0.0, 360.0, 30.0))
    directions = [towards] + [np.cos(t) * towards + np.sin(t) * (np.cos(p) * u + np.sin(p) * v)
                              for t in tilt[1:] for p in turn]
    best = None
    for offset in (1.3, 1.6):  # the nearer first; further out on a short neck
        for direction in directions:
            point = head.centre + offset * head.radius_mm * direction
            loops = section_mesh(vertices, faces, point, direction).loops()
            if not loops:
                continue
            loop = min(loops, key=lambda lp: np.linalg.norm(lp.mean(axis=0) - point))
            if np.linalg.norm(loop.mean(axis=0) - point) > 0.4 * head.radius_mm:
                continue  # the plane cuts the neck aslant, or the trochanters with it: not a neck section
            area = _loop_area(loop, direction)
            if best is None or area < best[0]:
                best = (area, loop.mean(axis=0))
        if best is not None:
            break
    if best is None:
        raise FitError("no section through the femoral neck")
    return np.vstack([head.centre, best[1]])


def _loop_area(loop: np.ndarray, normal: np.ndarray) -> float:
    return 0.5 * float(abs(np.cross(loop, np.roll(loop, -1, axis=0)).sum(axis=0) @ normal))


def _shaft_loop_centroid(vertices, faces, origin, z) -> np.ndarray:
    """Centroid of the largest loop of the section through ``origin`` perpendicular to ``z``."""
    loops = section_mesh(vertices, faces, origin, z).loops()
    if not loops:
        raise FitError("no section of the shaft at the proximal region boundary")
    loop = max(loops, key=lambda lp: _loop_area(lp, z))
    return loop.mean(axis=0)
