"""The embedded phantom: a synthetic right tibia built from a few morphometric parameters.

The bone is the zero level set of a smooth implicit function (a tube whose
cross-section flares from the shaft into the plateau and the plafond, a
tibial tuberosity, a medial malleolus and an anterior crest), meshed by
marching cubes. It is plausible enough for every stage to run on it, and its
parameters are the ones a surgeon measures on an X-ray or CT.
"""
from __future__ import annotations

import functools
from dataclasses import asdict, dataclass

import numpy as np

from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.mesh.intake import prepare_bone
from bonecad.mesh.sections import hull_edge_across, line_crossings, polygon_centroid
from bonecad.settings import MeshSettings, MorphometrySettings, UnitsSettings


@dataclass(frozen=True)
class TibiaParameters:
    """Morphometric parameters of the phantom tibia (mm), right leg, bone coordinates."""

    length_mm: float = 360.0
    plateau_width_mm: float = 76.0  # medial-lateral
    plateau_depth_mm: float = 50.0  # anterior-posterior
    plateau_posterior_offset_mm: float = 7.0  # plateau overhangs the shaft posteriorly
    shaft_width_mm: float = 22.0  # medial-lateral at mid-shaft
    shaft_depth_mm: float = 25.0  # anterior-posterior at mid-shaft
    distal_width_mm: float = 50.0
    distal_depth_mm: float = 40.0
    malleolus_length_mm: float = 14.0  # how far the medial malleolus reaches below the plafond
    tuberosity_height_mm: float = 9.0  # anterior prominence
    voxel_mm: float = 1.0  # marching-cubes resolution
    # Posterior slope of each condyle's surface, degrees from the plane perpendicular to the phantom's long
    # axis (positive: falls posteriorly), and the external torsion of the distal end against the plateau,
    # degrees (the sections turn progressively along the shaft). 0 leaves the phantom as it always was.
    medial_slope_deg: float = 0.0
    lateral_slope_deg: float = 0.0
    torsion_deg: float = 0.0


# The plafond's dome for the talus (mm high at the centre).
_PLAFOND_DOME_MM = 3.0


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _smooth_min(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1.0 - h) + a * h - k * h * (1.0 - h)


def _field(x: np.ndarray, y: np.ndarray, z: np.ndarray, p: TibiaParameters) -> np.ndarray:
    """Approximate signed distance (mm, negative inside) of the phantom at bone coordinates."""
    x, y = _twisted(x, y, z, p)
    body = _untwisted_body(x, y, z, p)
    # Tibial tuberosity: an ellipsoid on the anterior proximal shaft, its centre as deep below the body's own
    # anterior surface as the default phantom's (``_tuberosity_centre_y``).
    tz = p.length_mm - 0.11 * p.length_mm
    tub = np.sqrt(((x - 0.1 * p.plateau_width_mm) / 14.0) ** 2
                  + ((y - _tuberosity_centre_y(p)) / p.tuberosity_height_mm) ** 2
                  + ((z - tz) / 22.0) ** 2) - 1.0
    body = _smooth_min(body, tub * 10.0, 4.0)
    # Medial malleolus: medial (-x for a right tibia), reaching below the plafond.
    mal = np.sqrt(((x + 0.5 * p.distal_width_mm - 7.0) / 8.0) ** 2 + ((y - 2.0) / 11.0) ** 2
                  + ((z - 4.0) / (p.malleolus_length_mm + 4.0)) ** 2) - 1.0
    return _smooth_min(body, mal * 9.0, 4.0)


@functools.lru_cache(maxsize=256)
def _tuberosity_centre_y(p: TibiaParameters) -> float:
    """y (mm) of the tuberosity ellipsoid's centre: the default phantom's (half the shaft depth plus a fifth of
    the tuberosity's height), moved with the body's anterior surface under the tuberosity. Placed by the shaft
    depth alone, the ellipsoid of a phantom with a deep plateau or a small tuberosity sank into the
    metaphysis: 7.2 mm high, it stood 0.4 mm proud (the default's 9 mm: 5.2 mm)."""
    default = TibiaParameters()
    return (_anterior_surface_y(p) - _anterior_surface_y(default) + 0.5 * default.shaft_depth_mm
            + 0.2 * p.tuberosity_height_mm)


def _anterior_surface_y(p: TibiaParameters) -> float:
    """y (mm) where the body without tuberosity and malleolus (``_body_field``) is crossed outwards along +y
    at the tuberosity's x and height."""
    start = np.array([[0.1 * p.plateau_width_mm, 0.0, p.length_mm - 0.11 * p.length_mm]])
    return float(start[0, 1] + _first_exit(p, start, np.array([[0.0, 1.0, 0.0]]), 80.0, field=_body_field)[0])


def _twisted(x: np.ndarray, y: np.ndarray, z: np.ndarray, p: TibiaParameters) -> tuple[np.ndarray, np.ndarray]:
    """Torsion: the distal sections turn clockwise seen from above (external) by up to torsion_deg."""
    twist = np.radians(p.torsion_deg) * _smoothstep((0.70 * p.length_mm - z) / (0.54 * p.length_mm))
    return x * np.cos(twist) - y * np.sin(twist), x * np.sin(twist) + y * np.cos(twist)


def _body_field(x: np.ndarray, y: np.ndarray, z: np.ndarray, p: TibiaParameters) -> np.ndarray:
    """``_field`` without the tuberosity and the malleolus: shaft, metaphyses, plateau and plafond."""
    return _untwisted_body(*_twisted(x, y, z, p), z, p)


def _untwisted_body(x: np.ndarray, y: np.ndarray, z: np.ndarray, p: TibiaParameters) -> np.ndarray:
    """``_body_field`` in the twisted coordinates (``_twisted``)."""
    L = p.length_mm
    top = _smoothstep((z - 0.70 * L) / (0.26 * L))  # 0 in the shaft, 1 at the plateau
    bottom = _smoothstep((0.16 * L - z) / (0.14 * L))  # 1 at the plafond
    half_w = 0.5 * (p.shaft_width_mm + top * (p.plateau_width_mm - p.shaft_width_mm)
                    + bottom * (p.distal_width_mm - p.shaft_width_mm))
    half_d = 0.5 * (p.shaft_depth_mm + top * (p.plateau_depth_mm - p.shaft_depth_mm)
                    + bottom * (p.distal_depth_mm - p.shaft_depth_mm))
    cy = -p.plateau_posterior_offset_mm * top**2  # the plateau sits posterior to the shaft
    dx, dy = x, y - cy
    theta = np.arctan2(dy, dx)
    # Anterior crest in the shaft: a sharper anterior border (triangular section).
    crest = 1.0 + 0.22 * (1.0 - top) * (1.0 - bottom) * np.clip(np.sin(theta), 0.0, None) ** 6
    # Posterior intercondylar notch on the plateau.
    notch = 1.0 - 0.10 * top**4 * np.exp(-(((theta + 0.5 * np.pi) / 0.35) ** 2))
    rho = np.sqrt((dx / half_w) ** 2 + (dy / half_d) ** 2)
    radius = np.sqrt(half_w * half_d)
    body = (rho / (crest * notch) - 1.0) * radius
    # Ends: the plateau (two condylar dishes, the intercondylar eminence
    # between them) and the plafond (a dome for the talus), rounded into the sides.
    lateral_half = 0.25 * p.plateau_width_mm
    # each condyle's slope, blended across the intercondylar eminence (x = 0)
    slope = np.radians(p.medial_slope_deg + (p.lateral_slope_deg - p.medial_slope_deg) * _smoothstep((x + 5.0) / 10.0))
    top = (
        L
        + np.tan(slope) * (y - cy)
        - 3.0 * np.exp(-(((np.abs(x) - lateral_half) / (0.5 * lateral_half)) ** 2)
                       - ((y - cy) / (0.25 * p.plateau_depth_mm)) ** 2)
        + 5.0 * np.exp(-((x / 5.0) ** 2) - ((y - cy) / 8.0) ** 2)
    )
    bottom_surface = _PLAFOND_DOME_MM * np.exp(-((x / (0.25 * p.distal_width_mm)) ** 2)
                                               - ((y / (0.25 * p.distal_depth_mm)) ** 2))
    return -_smooth_min(-body, -np.maximum(z - top, bottom_surface - z), 3.0)


def _grid(p: TibiaParameters) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The marching-cubes grid (mm). Its top plane cuts the intercondylar eminence flat (the plateau's
    highest points), raised by what a sloped condyle's anterior rim rises."""
    h = p.voxel_mm
    margin = 3.0 * h
    # Grid offset by a fraction of a voxel: field values exactly zero at grid
    # points (the flat ends) make marching cubes emit non-manifold vertices.
    jitter = 0.371 * h
    half = 0.5 * max(p.plateau_width_mm, p.distal_width_mm) + 10.0
    rise = 0.5 * p.plateau_depth_mm * max(np.tan(np.radians(p.medial_slope_deg)),
                                          np.tan(np.radians(p.lateral_slope_deg)), 0.0)
    xs = np.arange(-half - margin, half + margin, h) + jitter
    ys = np.arange(-p.plateau_depth_mm - margin, p.plateau_depth_mm + margin, h) + jitter
    zs = np.arange(-p.malleolus_length_mm - 10.0, p.length_mm + margin + rise, h) + jitter
    return xs, ys, zs


#: voxels per side of the blocks ``_grid_field`` evaluates whole or not at all
_BLOCK_VOXELS = 2
#: a bound on the field's gradient (mm per mm): its terms are distances scaled by at most 10 / 7 (the tuberosity
#: ellipsoid) and the torsion turns a section by at most 0.01 rad per mm; twice that as a margin
_FIELD_LIPSCHITZ = 3.0


def _grid_field(xs: np.ndarray, ys: np.ndarray, zs: np.ndarray, p: TibiaParameters) -> np.ndarray:
    """``_field`` on the grid ``xs`` x ``ys`` x ``zs`` where marching cubes reads it: exactly in every block of
    ``_BLOCK_VOXELS`` voxels the surface may cross (judged from the field at the blocks' corners and its
    gradient bound), and elsewhere the blocks' sign times that reach. A cube of the grid lies in one block, so
    every cube the surface crosses has exact corners: the mesh is the one of the field evaluated everywhere, at
    a third of the cost (the grid is a box round a slender bone). The field of 26 phantoms (the tests' 20 varied
    ones, the default, four at 2 mm, one at 0.5 mm): 55-58 s of CPU evaluated everywhere, 25 s in blocks of 4
    voxels, 19 s in blocks of 2; the same meshes."""
    k, h = _BLOCK_VOXELS, float(xs[1] - xs[0])
    nodes = [np.unique(np.r_[np.arange(0, len(a), k), len(a) - 1]) for a in (xs, ys, zs)]
    cx, cy, cz = np.meshgrid(xs[nodes[0]], ys[nodes[1]], zs[nodes[2]], indexing="ij")
    corner = _field(cx, cy, cz, p)
    cells = [corner[a : corner.shape[0] - 1 + a, b : corner.shape[1] - 1 + b, c : corner.shape[2] - 1 + c]
             for a in (0, 1) for b in (0, 1) for c in (0, 1)]
    reach = _FIELD_LIPSCHITZ * k * h * np.sqrt(3.0)
    lo, hi = np.minimum.reduce(cells), np.maximum.reduce(cells)
    near_cell = (lo <= reach) & (hi >= -reach)
    # each grid index's blocks along one axis: two where it is a block boundary (the same one inside a block)
    sides = []
    for a, n in zip((xs, ys, zs), nodes):
        idx = np.arange(len(a))
        after = np.minimum(np.searchsorted(n, idx, side="right") - 1, len(n) - 2)
        sides.append((np.maximum(np.searchsorted(n, idx, side="left") - 1, 0), after))
    near = np.zeros((len(xs), len(ys), len(zs)), dtype=bool)
    for bx in sides[0]:
        for by in sides[1]:
            for bz in sides[2]:
                near |= near_cell[np.ix_(bx, by, bz)]
    inside = lo[np.ix_(sides[0][1], sides[1][1], sides[2][1])] < 0  # a far block: one sign at all its corners
    field = np.where(inside, -reach, reach)
    ix, iy, iz = np.nonzero(near)
    field[ix, iy, iz] = _field(xs[ix], ys[iy], zs[iz], p)
    return field


def phantom_tibia(params: TibiaParameters, *, settings: MeshSettings, plausible: UnitsSettings) -> BoneMesh:
    """A closed triangle mesh of the phantom (a right tibia in bone coordinates, mm)."""
    from skimage.measure import marching_cubes
    import trimesh

    p = params
    h = p.voxel_mm
    xs, ys, zs = _grid(p)
    field = _grid_field(xs, ys, zs, p).astype(np.float32)
    verts, faces, _, _ = marching_cubes(field, level=0.0, spacing=(h, h, h))
    verts += np.array([xs[0], ys[0], zs[0]])
    mesh = trimesh.Trimesh(verts, faces, process=True)
    trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=0.53, iterations=10)
    source = "phantom:" + ",".join(f"{k}={v:g}" for k, v in asdict(p).items())
    return prepare_bone(mesh.vertices, mesh.faces, source=source, units="mm", settings=settings, plausible=plausible)


# Where the design values are found on the exact implicit surface: coarse steps along a ray or a vertical
# line (mm), refined by bisection to well under a micrometre.
_COARSE_STEP_MM = 0.5
_BISECTIONS = 12
_RAYS = 720
#: the shaft levels of the design values: shares of the length above the plafond centre (percent)
DESIGN_SHAFT_LEVELS = (20, 35, 50, 65, 80)


def _first_exit(p: TibiaParameters, start: np.ndarray, direction: np.ndarray, reach: float,
                field=_field) -> np.ndarray:
    """Distance (mm) from each (n, 3) start point, inside the bone, along its (n, 3) unit direction to where
    the exact surface (of ``field``) is first crossed outwards; NaN where the start is outside or nothing is
    crossed within ``reach``."""
    steps = np.arange(0.0, reach + _COARSE_STEP_MM, _COARSE_STEP_MM)
    pts = start[:, None, :] + steps[None, :, None] * direction[:, None, :]
    outside = field(pts[..., 0], pts[..., 1], pts[..., 2], p) > 0
    first = np.argmax(outside, axis=1)
    found = ~outside[:, 0] & outside[np.arange(len(start)), first]
    lo, hi = steps[np.maximum(first - 1, 0)], steps[first]
    for _ in range(_BISECTIONS):
        mid = 0.5 * (lo + hi)
        q = start + mid[:, None] * direction
        out = field(q[:, 0], q[:, 1], q[:, 2], p) > 0
        lo, hi = np.where(out, lo, mid), np.where(out, mid, hi)
    return np.where(found, 0.5 * (lo + hi), np.nan)


def design_section(p: TibiaParameters, z: float, centre: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """(720, 2) x, y of the exact surface's section at height ``z`` (mm, phantom coordinates), seen as a
    star from ``centre`` (every section of the phantom is one from its axis, and the malleolus's from its own)."""
    angle = np.linspace(0.0, 2.0 * np.pi, _RAYS, endpoint=False)
    direction = np.column_stack([np.cos(angle), np.sin(angle), np.zeros(_RAYS)])
    start = np.tile([centre[0], centre[1], z], (_RAYS, 1))
    r = _first_exit(p, start, direction, 0.5 * max(p.plateau_width_mm, p.plateau_depth_mm) + 20.0)
    return start[:, :2] + r[:, None] * direction[:, :2]


def _vertical_profile(p: TibiaParameters, origin: np.ndarray, along: np.ndarray, z_from: float, reach: float
                      ) -> np.ndarray:
    """(k, 2) points (distance from ``origin`` (2,) along the horizontal unit ``along`` (2,), z) of the exact
    surface met going down from ``z_from`` in that vertical plane, every 0.05 mm within +- ``reach``."""
    u = np.arange(-reach, reach, 0.05)
    start = np.column_stack([origin + u[:, None] * along, np.full(len(u), z_from)])
    r = _first_exit(p, start, np.tile([0.0, 0.0, -1.0], (len(u), 1)), 30.0)
    ok = np.isfinite(r)
    return np.column_stack([u[ok], z_from - r[ok]])


def _articular_extent(profile: np.ndarray, level: float, s: MorphometrySettings) -> float:
    """Extent (mm) of a distal profile's part facing distally within the band about the plafond level."""
    slope = np.abs(np.gradient(profile[:, 1], profile[:, 0]))
    facing = (slope < np.tan(np.radians(s.plafond_facing_deg))) & (np.abs(profile[:, 1] - level) < s.plafond_band_mm)
    return float(np.ptp(profile[facing, 0]))


def design_measurements(p: TibiaParameters, settings: MorphometrySettings) -> dict[str, float]:
    """The phantom's design values under the definitions of ``bonecad measure`` (its ``PARAMETERS``), found on
    the exact implicit surface (never on a mesh): mm and degrees, in the phantom's coordinates (x lateral,
    y anterior, z along its long axis), with the anatomical frame's landmarks as the frame defines them:
    the plafond centre at the dome's area-weighted median height (``_PLAFOND_DOME_MM`` e^-2; the frame
    takes the median of the distal-facing surface, where the malleolus's tip adds a few mm^2) above the
    centroid of the sections 2-10 mm higher, the plateau centre on the surface above the plateau
    section's centre. The frame's axis leans back from the phantom's z by the plateau's posterior offset;
    the slopes are measured from the plane perpendicular to it. Lengths and sections ignore that lean
    (cos 1-2 deg: < 0.1 mm)."""
    s = settings
    L = p.length_mm
    z_cap = float(_grid(p)[2][-1])  # the grid's top plane cuts the eminence
    z_pf = _PLAFOND_DOME_MM * np.exp(-2.0)
    # (the section 2 mm up is a ring round the dome, not a star from the axis: its centroid is NaN, left out)
    xy_pf = np.nanmean([polygon_centroid(design_section(p, z_pf + dz)) for dz in (2.0, 4.0, 6.0, 8.0, 10.0)],
                       axis=0)
    cy = -p.plateau_posterior_offset_mm
    top = _first_exit(p, np.array([[0.0, cy, L - 10.0]]), np.array([[0.0, 0.0, 1.0]]), 30.0)[0]
    z_pc = min(L - 10.0 + top, z_cap) if np.isfinite(top) else z_cap
    axis = np.array([0.0, cy, z_pc]) - np.array([xy_pf[0], xy_pf[1], z_pf])
    length = float(np.linalg.norm(axis))
    lean = float(np.degrees(np.arctan2(-axis[1], axis[2])))
    m: dict[str, float] = {"length_mm": length}

    # the highest point of the plateau (the eminence, or a sloped condyle's anterior rim)
    gx, gy = np.meshgrid(np.arange(-0.5 * p.plateau_width_mm, 0.5 * p.plateau_width_mm, 1.0),
                         np.arange(cy - 0.5 * p.plateau_depth_mm, cy + 0.5 * p.plateau_depth_mm, 1.0))
    start = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, L - 10.0)])
    rise = _first_exit(p, start, np.tile([0.0, 0.0, 1.0], (len(start), 1)), 30.0)
    m["max_length_mm"] = min(L - 10.0 + float(np.nanmax(rise)), z_cap) + p.malleolus_length_mm

    plateau = design_section(p, z_pf + length - s.plateau_section_depth_mm, (0.0, cy))
    x_lo, x_hi = plateau[:, 0].min(), plateau[:, 0].max()
    width = x_hi - x_lo
    m["plateau_width_mm"] = float(width)
    condyles = {"medial": x_lo + s.condyle_share * width, "lateral": x_hi - s.condyle_share * width}
    for side, x in condyles.items():
        m[f"{side}_plateau_depth_mm"] = float(np.ptp(line_crossings(plateau, 0, x)))
    m["medial_posterior_slope_deg"] = p.medial_slope_deg - lean
    m["lateral_posterior_slope_deg"] = p.lateral_slope_deg - lean

    # the malleolus's centre turns with the distal end (the torsion)
    turn = np.radians(p.torsion_deg)
    centre = np.array([-0.5 * p.distal_width_mm + 7.0, 2.0])
    centre = np.array([centre[0] * np.cos(turn) + centre[1] * np.sin(turn),
                       -centre[0] * np.sin(turn) + centre[1] * np.cos(turn)])
    malleolus = polygon_centroid(design_section(p, z_pf - s.malleolus_depth_mm, (centre[0], centre[1])))
    ankle = (xy_pf - malleolus) / np.linalg.norm(xy_pf - malleolus)
    across = np.array([-ankle[1], ankle[0]])
    reach = 0.5 * max(p.distal_width_mm, p.distal_depth_mm) + 5.0
    m["plafond_width_mm"] = _articular_extent(_vertical_profile(p, xy_pf, ankle, z_pf + 10.0, reach), z_pf, s)
    m["plafond_depth_mm"] = _articular_extent(_vertical_profile(p, xy_pf, across, z_pf + 10.0, reach), z_pf, s)
    # the widest distal sections lie above the dome (the malleolus bulges most at its centre, 4 mm up)
    levels = np.arange(_PLAFOND_DOME_MM + 1.0, z_pf + s.distal_zone_mm, 1.0)
    distal = np.vstack([design_section(p, z) for z in levels])
    m["bimalleolar_width_mm"] = float(np.ptp(distal @ ankle))

    for pct in DESIGN_SHAFT_LEVELS:
        loop = design_section(p, z_pf + pct / 100.0 * length, (0.0, 0.0))
        m[f"shaft_ml_{pct}_mm"] = float(np.ptp(loop[:, 0]))
        m[f"shaft_ap_{pct}_mm"] = float(np.ptp(loop[:, 1]))

    a, b = hull_edge_across(plateau, 0, 0.5 * (condyles["medial"] + condyles["lateral"]), -1.0)
    proximal = (b - a) * np.sign(b[0] - a[0])
    distal_axis = xy_pf - malleolus
    m["torsion_deg"] = float(np.degrees(np.arctan2(proximal[1], proximal[0])
                                        - np.arctan2(distal_axis[1], distal_axis[0])))
    return m


#: the span (mm) each parameter of a varied phantom is drawn from, uniformly: the adult ranges of tibial length
#: (320-420 mm), plateau width (68-84 mm) and depth, shaft and plafond widths and depths, malleolus and
#: tuberosity, each about +-12 % (+-25 % for the small features) around the default phantom's value
VARIED_SPANS_MM: dict[str, tuple[float, float]] = {
    "length_mm": (320.0, 420.0),
    "plateau_width_mm": (68.0, 84.0),
    "plateau_depth_mm": (44.0, 56.0),
    "plateau_posterior_offset_mm": (5.0, 9.0),
    "shaft_width_mm": (19.0, 25.0),
    "shaft_depth_mm": (22.0, 28.0),
    "distal_width_mm": (44.0, 56.0),
    "distal_depth_mm": (35.0, 45.0),
    "malleolus_length_mm": (11.0, 17.0),
    "tuberosity_height_mm": (7.0, 11.0),
}


def varied_parameters(count: int, *, seed: int = 0) -> list[TibiaParameters]:
    """``count`` phantom parameter sets, each parameter drawn uniformly from ``VARIED_SPANS_MM`` (seeded:
    the same ``seed`` gives the same cohort)."""
    rng = np.random.default_rng(seed)
    lo, hi = (np.array([span[i] for span in VARIED_SPANS_MM.values()]) for i in (0, 1))
    draws = lo + (hi - lo) * rng.random((count, len(VARIED_SPANS_MM)))
    return [TibiaParameters(**dict(zip(VARIED_SPANS_MM, map(float, row)))) for row in draws]
