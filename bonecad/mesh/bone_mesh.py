"""The polygonal model every later stage reads: one closed bone surface in mm."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from bonecad.mesh.sampling import triangle_areas


@dataclass(frozen=True)
class BodyInfo:
    """One connected body found in the input (the tibia, a fibula, a fragment)."""

    triangles: int
    volume_mm3: float
    length_mm: float
    centroid: np.ndarray  # (3,) mm, input coordinates
    role: str  # "tibia", "fibula", "fragment", "broken piece"


@dataclass(frozen=True)
class BoneMesh:
    """A closed, cleaned triangle mesh of one bone, in the input's coordinates (mm).

    vertices : (n, 3) float64, mm
    faces : (m, 3) int64, counter-clockwise seen from outside (normals point out)
    """

    vertices: np.ndarray
    faces: np.ndarray
    source: str = ""
    units: str = "mm"
    bodies: tuple[BodyInfo, ...] = ()
    repairs: tuple[str, ...] = ()
    watertight: bool = True
    extra: dict = field(default_factory=dict)

    @property
    def triangle_count(self) -> int:
        return int(len(self.faces))

    def to_trimesh(self):
        """A trimesh.Trimesh view of this mesh (no processing)."""
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=False)

    def face_areas(self) -> np.ndarray:
        """(m,) triangle areas in mm^2."""
        return triangle_areas(self.vertices, self.faces)
