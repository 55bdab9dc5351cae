"""Landmarks of bones other than the tibia, carried by the anatomical frame (scanner coordinates, mm)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Sphere:
    """A least-squares sphere (mm): centre, radius, RMS residual, and the share of a whole sphere its
    points cover (their area over 4 pi r^2)."""

    centre: np.ndarray
    radius_mm: float
    rms_mm: float
    coverage: float


@dataclass(frozen=True)
class FemurLandmarks:
    """The femur's own entities, scanner coordinates (mm).

    condyle_centres, epicondyles : rows medial, lateral. points : the raters' 22 landmarks by abbreviation
    (``anatomy.femur_points.NAMES``; MEC and LEC are the epicondyles). isb_axes : rows x (anterior), y (proximal,
    epicondyle midpoint -> head centre), z (right), origin at the head centre (Wu et al. 2002).
    """

    head: Sphere
    neck_axis: np.ndarray  # (2, 3) head centre, centroid of the narrowest neck section
    knee_centre: np.ndarray  # (3,)
    condyle_centres: np.ndarray  # (2, 3) posterior condyle sphere centres
    condyle_radii_mm: np.ndarray  # (2,)
    epicondyles: np.ndarray  # (2, 3)
    shaft_axis: np.ndarray  # (2, 3) points of the anatomical axis at the shaft's ends
    isb_axes: np.ndarray  # (3, 3)
    points: dict[str, np.ndarray] = field(default_factory=dict)  # abbreviation -> (3,)

    @property
    def neck_shaft_angle_deg(self) -> float:
        """Angle between the neck axis (towards the head) and the shaft axis (towards the knee), degrees."""
        neck = self.neck_axis[0] - self.neck_axis[1]
        down = self.shaft_axis[0] - self.shaft_axis[1]
        cos = neck @ down / np.linalg.norm(neck) / np.linalg.norm(down)
        return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))

    def as_dict(self) -> dict:
        r = lambda a: np.round(np.asarray(a, dtype=float), 6).tolist()  # noqa: E731
        return {
            "head": {"centre": r(self.head.centre), "radius_mm": round(self.head.radius_mm, 4),
                     "rms_residual_mm": round(self.head.rms_mm, 4), "sphere_coverage": round(self.head.coverage, 4)},
            "neck_axis": {"start_head_centre": r(self.neck_axis[0]), "end_neck_centroid": r(self.neck_axis[1])},
            "neck_shaft_angle_deg": round(self.neck_shaft_angle_deg, 3),
            "knee_centre": r(self.knee_centre),
            "posterior_condyles": {"medial_centre": r(self.condyle_centres[0]),
                                   "lateral_centre": r(self.condyle_centres[1]),
                                   "radii_mm": r(self.condyle_radii_mm)},
            "transepicondylar_axis": {"medial_epicondyle": r(self.epicondyles[0]),
                                      "lateral_epicondyle": r(self.epicondyles[1])},
            "anatomical_axis": {"distal": r(self.shaft_axis[0]), "proximal": r(self.shaft_axis[1])},
            "isb_frame": {"origin": r(self.head.centre), "x_anterior": r(self.isb_axes[0]),
                          "y_proximal": r(self.isb_axes[1]), "z_right": r(self.isb_axes[2])},
            "landmarks": {name: r(p) for name, p in self.points.items()},
        }
