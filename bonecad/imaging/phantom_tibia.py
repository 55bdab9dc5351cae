"""The embedded phantom: a synthetic right tibia built from a few morphometric parameters.

The bone is the zero level set of a smooth implicit function (a tube whose
cross-section flares from the shaft into the plateau and the plafond, a
tibial tuberosity, a medial malleolus and an anterior crest), meshed by
marching cubes. It is plausible enough for every stage to run on it, and its
parameters are the ones a surgeon measures on an X-ray or CT.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.mesh.intake import prepare_bone
from bonecad.settings import MeshSettings, UnitsSettings


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


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _smooth_min(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1.0 - h) + a * h - k * h * (1.0 - h)


def _field(x: np.ndarray, y: np.ndarray, z: np.ndarray, p: TibiaParameters) -> np.ndarray:
    """Approximate signed distance (mm, negative inside) of the phantom at bone coordinates."""
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
    top = (
        L
        - 3.0 * np.exp(-(((np.abs(x) - lateral_half) / (0.5 * lateral_half)) ** 2)
                       - ((y - cy) / (0.25 * p.plateau_depth_mm)) ** 2)
        + 5.0 * np.exp(-((x / 5.0) ** 2) - ((y - cy) / 8.0) ** 2)
    )
    bottom_surface = 3.0 * np.exp(-((x / (0.25 * p.distal_width_mm)) ** 2) - ((y / (0.25 * p.distal_depth_mm)) ** 2))
    body = -_smooth_min(-body, -np.maximum(z - top, bottom_surface - z), 3.0)
    # Tibial tuberosity: an ellipsoid on the anterior proximal shaft.
    tz = L - 0.11 * L
    tub = np.sqrt(((x - 0.1 * p.plateau_width_mm) / 14.0) ** 2
                  + ((y - (0.5 * p.shaft_depth_mm + 0.2 * p.tuberosity_height_mm)) / p.tuberosity_height_mm) ** 2
                  + ((z - tz) / 22.0) ** 2) - 1.0
    body = _smooth_min(body, tub * 10.0, 4.0)
    # Medial malleolus: medial (-x for a right tibia), reaching below the plafond.
    mal = np.sqrt(((x + 0.5 * p.distal_width_mm - 7.0) / 8.0) ** 2 + ((y - 2.0) / 11.0) ** 2
                  + ((z - 4.0) / (p.malleolus_length_mm + 4.0)) ** 2) - 1.0
    body = _smooth_min(body, mal * 9.0, 4.0)
    return body


def phantom_tibia(params: TibiaParameters, *, settings: MeshSettings, plausible: UnitsSettings) -> BoneMesh:
    """A closed triangle mesh of the phantom (a right tibia in bone coordinates, mm)."""
    from skimage.measure import marching_cubes
    import trimesh

    p = params
    h = p.voxel_mm
    margin = 3.0 * h
    # Grid offset by a fraction of a voxel: field values exactly zero at grid
    # points (the flat ends) make marching cubes emit non-manifold vertices.
    jitter = 0.371 * h
    half = 0.5 * max(p.plateau_width_mm, p.distal_width_mm) + 10.0
    xs = np.arange(-half - margin, half + margin, h) + jitter
    ys = np.arange(-p.plateau_depth_mm - margin, p.plateau_depth_mm + margin, h) + jitter
    zs = np.arange(-p.malleolus_length_mm - 10.0, p.length_mm + margin, h) + jitter
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
    field = _field(X, Y, Z, p).astype(np.float32)
    verts, faces, _, _ = marching_cubes(field, level=0.0, spacing=(h, h, h))
    verts += np.array([xs[0], ys[0], zs[0]])
    mesh = trimesh.Trimesh(verts, faces, process=True)
    trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=0.53, iterations=10)
    source = "phantom:" + ",".join(f"{k}={v:g}" for k, v in asdict(p).items())
    return prepare_bone(mesh.vertices, mesh.faces, source=source, units="mm", settings=settings, plausible=plausible)


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
