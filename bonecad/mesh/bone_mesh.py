"""The polygonal model every later stage reads: one closed bone surface in mm."""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from bonecad.mesh.closest import TriangleLocator
from bonecad.mesh.sampling import triangle_areas
from bonecad.splines.tspline.fit import voxel_step_mm


@dataclass(frozen=True)
class BodyInfo:
    """One connected body found in the input (the tibia, a fibula, a fragment)."""

    triangles: int
    volume_mm3: float
    length_mm: float
    centroid: np.ndarray  # (3,) mm, input coordinates
    role: str  # "tibia", "fibula", "femur", "patella", "talus", "foot bone", "fragment", "broken piece"


@dataclass(frozen=True)
class BoneMesh:
    """A closed, cleaned triangle mesh of one bone, in the input's coordinates (mm).

    vertices : (n, 3) float64, mm
    faces : (m, 3) int64, counter-clockwise seen from outside (normals point out)
    segmented : True when bonecad segmented it from a CT volume: the polygonal
        model the CAD models are fitted to, written as bone.stl beside them
    working : a simplified copy of the same surface for the stages that need the shape, not every
        triangle (``mesh.working.with_working_copy``); None when the mesh is no denser than that
    """

    vertices: np.ndarray
    faces: np.ndarray
    source: str = ""
    units: str = "mm"
    bodies: tuple[BodyInfo, ...] = ()
    repairs: tuple[str, ...] = ()
    watertight: bool = True
    segmented: bool = False
    extra: dict = field(default_factory=dict)
    working: BoneMesh | None = None
    #: closest-point trees by the ids of the arrays they were built on (held with them), shared by the
    #: copies ``dataclasses.replace`` makes (the tree of a dense mesh takes seconds); not pickled
    trees: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def locator(self) -> TriangleLocator:
        """The closest-point tree of this mesh (built at the first use, then kept; not pickled)."""
        key = (id(self.vertices), id(self.faces))
        if key not in self.trees:
            self.trees[key] = (self.vertices, self.faces, TriangleLocator(self.vertices, self.faces))
        return self.trees[key][2]

    @cached_property
    def voxel_step_mm(self) -> float:
        """The voxel size (mm) of a staircase mesh, 0.0 for any other (``voxel_step_mm``; computed at the first
        use, then kept: the T-spline fit and its noise read it)."""
        return voxel_step_mm(self.vertices)

    def __getstate__(self) -> dict:
        return {**self.__dict__, "trees": {}}

    @property
    def work(self) -> BoneMesh:
        """The mesh the frame, the curves, the fit and the pictures work on: the working copy, or this mesh."""
        return self.working if self.working is not None else self

    @property
    def triangle_count(self) -> int:
        """Number of triangles."""
        return int(len(self.faces))

    def to_trimesh(self):
        """A trimesh.Trimesh view of this mesh (no processing)."""
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=False)

    def face_areas(self) -> np.ndarray:
        """(m,) triangle areas in mm^2."""
        return triangle_areas(self.vertices, self.faces)

    def summary(self) -> dict:
        """JSON-ready input summary for frame.json and the report: file, units, bodies, repairs."""
        return {
            "file": self.source,
            "units": self.units,
            "triangles": self.triangle_count,
            "watertight": self.watertight,
            "bodies": [
                {
                    "role": b.role,
                    "triangles": b.triangles,
                    "volume_mm3": round(b.volume_mm3, 1),
                    "length_mm": round(b.length_mm, 1),
                    "centroid": np.round(b.centroid, 3).tolist(),
                }
                for b in self.bodies
            ],
            "repairs": list(self.repairs),
            **({"segmentation_level_hu": round(float(self.extra["level_hu"]), 1),
                "segmented_on_voxels_mm": " x ".join(f"{v:.2f}" for v in self.extra["voxel_mm"]),
                "scan_voxels_mm": " x ".join(f"{v:.2f}" for v in self.extra["scan_voxel_mm"])}
               if self.segmented else {}),
            **({"working_copy": {"triangles": self.working.triangle_count, **self.working.extra}}
               if self.working is not None else {}),
        }
