"""The 22 femoral landmarks raters pick (Fischer et al. 2020, Sci. Rep. 10:20859), found from the femur's
anatomy: docs/guides/femur-landmarks.md gives each definition and how close it comes to five raters.

Most are where a ray from an anatomical centre leaves the bone, in a direction fixed in a local anatomical
frame: the head points from the head's centre, the neck isthmus points from the centroid of the neck's
narrowest section, the condyle points from the centres of the posterior condyle spheres. The directions
are the raters' mean directions on the ten landmarked femurs of ../shared/data/femur_pairs, expressed in
those frames (lateral, anterior, proximal components, the same for a left and a right femur). The
trochanters, the intertrochanteric crest and the epicondyles are prominences: extreme points within an
anatomical window. All points are on the surface, scanner coordinates (mm).
"""
from __future__ import annotations

import numpy as np

from bonecad.anatomy.landmarks import Sphere
from bonecad.errors import FitError
from bonecad.mesh.sections import section_mesh, section_stack

#: abbreviation -> name, in the raters' order (the README of ../shared/data/femur_pairs)
NAMES = {
    "SFH": "superior femoral head", "AFH": "anterior femoral head", "LFH": "lateral femoral head",
    "PFH": "posterior femoral head", "MFH": "medial femoral head", "IFH": "inferior femoral head",
    "SNI": "superior neck isthmus", "ANI": "anterior neck isthmus", "INI": "inferior neck isthmus",
    "PNI": "posterior neck isthmus", "SGT": "superior greater trochanter", "LT": "lesser trochanter",
    "PITC": "posterior intertrochanteric crest", "PLC": "posterior lateral condyle",
    "PMC": "posterior medial condyle", "PPLC": "proximoposterior lateral condyle",
    "PPMC": "proximoposterior medial condyle", "LEC": "lateral epicondyle", "MEC": "medial epicondyle",
    "ICN": "intercondylar notch", "DLC": "distal lateral condyle", "DMC": "distal medial condyle",
}

# Head points: rays from the head centre. Frame "hip": z the mechanical axis (knee centre -> head centre),
# x the neck's direction (head -> neck) across it, y anterior. Frame "neck": x along the neck axis
# (head -> neck), y anterior across it, z up across it. The raters' mean direction on ten femurs (their
# spread about it, median / max, degrees): SFH 2.1/4.6, AFH 2.7/4.2, PFH 1.9/3.4, MFH 3.8/8.3 (hip),
# LFH 4.8/8.7, IFH 6.5/12.4 (neck: the lateral and inferior points lie where the head meets the neck).
_HEAD_RAYS = {
    "SFH": ("hip", (0.02, 0.01, 1.0)), "AFH": ("hip", (-0.01, 1.0, 0.08)), "PFH": ("neck", (-0.1, -1.0, 0.0)),
    "MFH": ("hip", (-0.99, 0.01, 0.15)), "LFH": ("neck", (0.32, 0.02, 0.95)), "IFH": ("neck", (0.12, -0.03, -0.99)),
}
# Neck isthmus: the section across the neck axis where the neck is narrowest. Its area changes by 1-2 %
# over 0.2-0.4 head radii there, so the level is the middle of the levels whose area is within this
# factor of the least (the raters' sections lie 0.91-1.18 radii from the head centre) ...
_ISTHMUS_AREA_FACTOR = 1.05
_ISTHMUS_SEARCH_RADII = (0.7, 1.6)
# ... and the points are where rays from its centroid, at these angles from anterior towards superior in
# the "neck" frame, cross its outline (the raters' mean angles; spread 3-5 degrees, ANI's 4-18).
_ISTHMUS_ANGLES_DEG = {"SNI": 87.0, "ANI": 9.0, "INI": -90.0, "PNI": 179.0}
# Condyle points: rays from the centre of each posterior condyle's sphere, in the distal frame: z along the
# distal shaft's centreline (the centroids of the sections _DISTAL_SHAFT_MM above the knee centre), x along
# the posterior condylar axis (medial -> lateral condyle centre) across it, y anterior. The raters' spread
# about the mean direction (median / max, degrees): PLC 3.7/8.3, PMC 3.5/5.0, PPLC 6.2/9.3, PPMC 5.9/9.6,
# DLC 7.4/13.4, DMC 4.1/5.8. (In the bone frame, whose z is the whole shaft's axis, 51 of these 60
# landmark-femur pairs were within the raters' spread; in this frame 58: the shaft's bow tilts the distal
# femur against the whole shaft's axis by up to several degrees.)
_DISTAL_SHAFT_MM = (30.0, 100.0)
_CONDYLE_RAYS = {
    "PLC": (1, (0.05, -0.98, -0.18)), "PMC": (0, (-0.04, -0.97, -0.24)),
    "PPLC": (1, (-0.16, -0.77, 0.62)), "PPMC": (0, (-0.09, -0.76, 0.64)),
    "DLC": (1, (0.13, 0.43, -0.89)), "DMC": (0, (0.11, 0.41, -0.91)),
}
# The top of a prominence (the greater and lesser trochanters): the vertex nearest the middle of the surface
# within this (mm) of its farthest point (SGT 10 and LT 8 of 10 femurs within the raters' spread at 0.5-2 mm;
# 9 and 7 with the farthest vertex alone).
_TOP_CAP_MM = 1.0
# The epicondyles are sought about lines parallel to the posterior condylar axis (through the two condyle
# spheres' centres) this far (mm) anterior and proximal of each condyle's centre: the raters' mean offsets
# (SD 1.6-2.2 mm across the ten femurs); rows medial, lateral.
_EPICONDYLE_OFFSETS_MM = ((8.3, 5.1), (3.9, 5.2))
# The notch: in the section across the posterior condylar axis through the middle of the two condyle
# centres (which lies on the notch's roof), walking from there forwards down the roof, the first point where
# the outline, over the next 3 mm, falls less than 25 degrees below the horizontal: the roof's anterior
# end, where it meets the trochlea's distal surface (the raters' point is within 0.5-3 mm of it).
_NOTCH_STEP_MM = 3.0
_NOTCH_SLOPE_DEG = 25.0


def _ray_exit(vertices: np.ndarray, faces: np.ndarray, start: np.ndarray, direction: np.ndarray,
              reach: float) -> np.ndarray:
    """The first point beyond ``start`` (within ``reach`` mm) where the ray along ``direction`` crosses the
    surface."""
    from bonecad.anatomy.frame import _ray_hits

    direction = direction / np.linalg.norm(direction)
    near = faces[np.linalg.norm(vertices[faces].mean(axis=1) - start, axis=1) < reach]
    hits = _ray_hits(vertices, near, start, direction)
    hits = hits[hits > 1e-6]
    if not len(hits):
        raise FitError(f"no surface within {reach:.0f} mm of {np.round(start, 1).tolist()} along "
                       f"{np.round(direction, 3).tolist()}")
    return start + hits[0] * direction


def _hip_frames(head: Sphere, neck_centre: np.ndarray, knee: np.ndarray, anterior: np.ndarray
                ) -> dict[str, np.ndarray]:
    """The "hip" and "neck" frames (rows x, y, z) of the module docstring."""
    c = head.centre
    z = (c - knee) / np.linalg.norm(c - knee)
    neck = (neck_centre - c) / np.linalg.norm(neck_centre - c)
    x = neck - (neck @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    y *= np.sign(y @ anterior)
    ny = np.cross(neck, z)
    ny /= np.linalg.norm(ny)
    ny *= np.sign(ny @ anterior)
    nz = np.cross(neck, ny)
    nz *= np.sign(nz @ z)
    return {"hip": np.vstack([x, y, z]), "neck": np.vstack([neck, ny, nz])}


def distal_frame(vertices, faces, knee: np.ndarray, axes: np.ndarray, condyle_centres: np.ndarray) -> np.ndarray:
    """The distal femur's frame (rows x lateral, y anterior, z proximal; see ``_CONDYLE_RAYS``)."""
    levels = np.linspace(*_DISTAL_SHAFT_MM, 8)
    _, centroids = section_stack(vertices, faces, knee, axes[2], levels)
    centroids = centroids[np.isfinite(centroids).all(axis=1)]
    if len(centroids) < 3:
        raise FitError("no sections of the distal femoral shaft")
    _, _, vt = np.linalg.svd(centroids - centroids.mean(axis=0))
    z = vt[0] * np.sign(vt[0] @ axes[2])
    x = condyle_centres[1] - condyle_centres[0]
    x = x - (x @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    y *= np.sign(y @ axes[1])
    return np.vstack([x, y, z])


def _loop_area(loop: np.ndarray, normal: np.ndarray) -> float:
    return 0.5 * float(abs(np.cross(loop, np.roll(loop, -1, axis=0)).sum(axis=0) @ normal))


def _isthmus(vertices, faces, head: Sphere, neck: np.ndarray) -> np.ndarray:
    """The outline (p, 3) of the neck's narrowest section across the neck axis (rows of ``neck``: axis
    towards the neck first)."""
    c, r, n = head.centre, head.radius_mm, neck[0]
    levels = np.arange(_ISTHMUS_SEARCH_RADII[0], _ISTHMUS_SEARCH_RADII[1] + 1e-9, 0.02) * r

    def section(level: float) -> np.ndarray | None:
        point = c + level * n
        loops = section_mesh(vertices, faces, point, n).loops()
        if not loops:
            return None
        loop = min(loops, key=lambda lp: np.linalg.norm(lp.mean(axis=0) - point))
        return loop if np.linalg.norm(loop.mean(axis=0) - point) < 0.4 * r else None

    areas = np.array([_loop_area(lp, n) if (lp := section(h)) is not None else np.inf for h in levels])
    if not np.isfinite(areas).any():
        raise FitError("no section across the femoral neck")
    narrow = levels[areas <= _ISTHMUS_AREA_FACTOR * areas.min()]
    loop = section(float(narrow.mean()))
    if loop is None:
        raise FitError("no section across the femoral neck at its isthmus")
    return loop


def _top(vertices: np.ndarray, cap: np.ndarray) -> np.ndarray:
    """The vertex of the boolean mask ``cap`` nearest the mean of its vertices."""
    points = vertices[cap]
    return points[int(np.argmin(np.linalg.norm(points - points.mean(axis=0), axis=1)))]


def _outline_point(loop: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """The vertex of a section outline seen from its centroid closest to ``direction``."""
    rel = loop - loop.mean(axis=0)
    return loop[int(np.argmax(rel @ direction / np.linalg.norm(rel, axis=1)))]


def femur_points(vertices: np.ndarray, faces: np.ndarray, *, head: Sphere, neck_axis: np.ndarray,
                 knee: np.ndarray, axes: np.ndarray, shaft_axis: np.ndarray, condyle_centres: np.ndarray,
                 condyle_radii: np.ndarray, epicondyle_reach_mm: float, epicondyle_cap_mm: float
                 ) -> dict[str, np.ndarray]:
    """The 22 landmarks (abbreviation -> point on the surface, scanner mm) of ``NAMES``.

    neck_axis : the head centre and the centroid of the neck's narrowest section (``anatomy.femur``).
    axes : the bone frame's rows lateral, anterior, proximal. condyle_centres, condyle_radii : the posterior
    condyle spheres (rows medial, lateral). epicondyle_reach_mm, epicondyle_cap_mm : see ``_epicondyles``.
    """
    hip_faces = faces[np.linalg.norm(vertices[faces].mean(axis=1) - head.centre, axis=1) < 3.0 * head.radius_mm]
    frames = _hip_frames(head, neck_axis[1], knee, axes[1])
    loop = _isthmus(vertices, hip_faces, head, frames["neck"])
    reach = 3.0 * head.radius_mm
    out: dict[str, np.ndarray] = {}
    for name, (frame, d) in _HEAD_RAYS.items():
        out[name] = _ray_exit(vertices, faces, head.centre, np.asarray(d) @ frames[frame], reach)

    neck = frames["neck"]
    for name, angle in _ISTHMUS_ANGLES_DEG.items():
        a = np.radians(angle)
        out[name] = _outline_point(loop, np.cos(a) * neck[1] + np.sin(a) * neck[2])

    out.update(_trochanters(vertices, faces, head, frames["hip"], shaft_axis, axes, out))

    distal = distal_frame(vertices, faces, knee, axes, condyle_centres)
    for name, (i, d) in _CONDYLE_RAYS.items():
        out[name] = _ray_exit(vertices, faces, condyle_centres[i], np.asarray(d) @ distal,
                              3.0 * float(condyle_radii[i]))
    out["ICN"] = _notch(vertices, faces, condyle_centres, axes)
    out["MEC"], out["LEC"] = _epicondyles(vertices, condyle_centres, axes, epicondyle_reach_mm, epicondyle_cap_mm)
    return {name: out[name] for name in NAMES}


def _trochanters(vertices, faces, head: Sphere, hip: np.ndarray, shaft_axis: np.ndarray, axes: np.ndarray,
                 found: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """SGT, LT and PITC: prominences of the proximal femur (``found`` holds the neck isthmus points)."""
    c, r = head.centre, head.radius_mm
    local = (vertices - c) @ hip.T  # x towards the neck, y anterior, z up the mechanical axis
    out = {}
    # the greater trochanter's top: of the bone lateral of the neck (beyond 1.5 head radii), the middle of the
    # surface within _TOP_CAP_MM of the highest point along the mechanical axis
    beyond = local[:, 0] > 1.5 * r
    if not beyond.any():
        raise FitError("no bone lateral of the femoral neck (greater trochanter)")
    out["SGT"] = _top(vertices, beyond & (local[:, 2] >= local[beyond, 2].max() - _TOP_CAP_MM))
    # the lesser trochanter: the top of the prominence farthest from the shaft axis towards the back and the
    # inside (110-160 degrees from lateral towards posterior; the raters' 113-152), 1.5-4.5 head radii below
    # the head centre (its top: _TOP_CAP_MM)
    a, b = shaft_axis
    d = (b - a) / np.linalg.norm(b - a)
    rel = vertices - a - ((vertices - a) @ d)[:, None] * d
    across = rel @ axes[:2].T  # lateral, anterior
    angle = np.degrees(np.arctan2(across[:, 1], across[:, 0]))
    radial = np.hypot(across[:, 0], across[:, 1])
    window = (local[:, 2] < -1.5 * r) & (local[:, 2] > -4.5 * r) & (angle < -110.0) & (angle > -160.0)
    if not window.any():
        raise FitError("no bone behind and inside the shaft below the femoral neck (lesser trochanter)")
    out["LT"] = _top(vertices, window & (radial >= radial[window].max() - _TOP_CAP_MM))
    # the intertrochanteric crest: the most posterior point (10 degrees towards the head) of the section
    # across the mechanical axis a fifth of the way down from the neck's inferior isthmus to the lesser
    # trochanter, lateral of the head centre
    z_ini = float((found["INI"] - c) @ hip[2])
    level = z_ini + 0.2 * (float((out["LT"] - c) @ hip[2]) - z_ini)
    loops = section_mesh(vertices, faces, c + level * hip[2], hip[2]).loops()
    outline = np.vstack(loops) if loops else np.zeros((0, 3))
    lateral = outline[(outline - c) @ hip[0] > 0.5 * r]
    if not len(lateral):
        raise FitError("no section through the intertrochanteric crest")
    back = np.array([-np.sin(np.radians(10.0)), -np.cos(np.radians(10.0)), 0.0]) @ hip
    out["PITC"] = lateral[int(np.argmax(lateral @ back))]
    return out


def _epicondyles(vertices, condyle_centres: np.ndarray, axes: np.ndarray, reach: float, cap: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The medial and lateral epicondyles: the tops of the prominences farthest out along the posterior
    condylar axis among the surface within ``reach`` mm of the lines ``_EPICONDYLE_OFFSETS_MM`` give; the top
    is the vertex nearest the middle of the surface within ``cap`` mm of the farthest point (a broad,
    flat epicondyle has no single farthest point). The articular rims of the condyles and osteophytes on
    them lie farther from those lines and are never taken for the epicondyles."""
    d = condyle_centres[1] - condyle_centres[0]
    d /= np.linalg.norm(d)
    anterior = axes[1] - (axes[1] @ d) * d
    anterior /= np.linalg.norm(anterior)
    up = np.cross(d, anterior)
    up *= np.sign(up @ axes[2])
    found = []
    for centre, (ahead, above), outward in zip(condyle_centres, _EPICONDYLE_OFFSETS_MM, (-1.0, 1.0)):
        rel = vertices - (centre + ahead * anterior + above * up)
        along = outward * (rel @ d)
        near = np.linalg.norm(rel - (rel @ d)[:, None] * d, axis=1) < reach
        if not near.any():
            raise FitError("no surface near the posterior condylar axis at an epicondyle")
        top = vertices[near & (along >= along[near].max() - cap)]
        spread = top - top.mean(axis=0)
        found.append(top[int(np.argmin(np.linalg.norm(spread - (spread @ d)[:, None] * d, axis=1)))])
    return found[0], found[1]


def _notch(vertices, faces, condyle_centres: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """The intercondylar notch point (see ``_NOTCH_SLOPE_DEG``)."""
    middle = condyle_centres.mean(axis=0)
    across = (condyle_centres[1] - condyle_centres[0]) / np.linalg.norm(condyle_centres[1] - condyle_centres[0])
    loops = section_mesh(vertices, faces, middle, across).loops()
    if not loops:
        raise FitError("no section through the intercondylar notch")
    loop = min(loops, key=lambda lp: float(np.linalg.norm(lp - middle, axis=1).min()))
    local = (loop - middle) @ axes.T
    n = len(loop)
    start = int(np.argmin(np.linalg.norm(local, axis=1)))
    step = 1 if local[(start + 3) % n, 1] > local[(start - 3) % n, 1] else -1  # walk forwards
    order = (start + step * np.arange(n)) % n
    path = local[order]
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))]
    for j in range(n):
        k = int(np.searchsorted(arc, arc[j] + _NOTCH_STEP_MM))
        if k >= n or arc[j] > 60.0:
            break
        chord = path[k] - path[j]
        if np.degrees(np.arctan2(-chord[2], chord[1])) < _NOTCH_SLOPE_DEG and path[j, 2] < -3.0:
            return loop[order[j]]
    raise FitError("no anterior end of the intercondylar notch's roof within 60 mm of the condyle centres")
