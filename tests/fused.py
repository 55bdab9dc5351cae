"""A tibia mesh fused to its fibula at the proximal tibiofibular joint, as thresholding a CT gives.

TLEM2's CT mesh holds both bones; its fibula comes within 0.17 mm of the
tibia at the proximal tibiofibular joint (about 1.5-2 mm at the distal one).
Voxelising both bodies on one 1 mm grid (partial-volume occupancy >= 0.5, as a
threshold does) closes the proximal joint space, and marching cubes of that
mask gives one closed body: tibia and fibula joined near the plateau, the
fibula's lateral malleolus hanging beside the plafond. Nothing in the mesh
intake can tell the fibula apart then.

The grid is the bounding box of both bodies plus two voxels; the build is
deterministic (no randomness, fixed grid) and takes about a second.

``python -m tests.fused OUT.stl`` writes the mesh (for reproducing by hand).
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .conftest import TIBIA_DIR

SOURCE = TIBIA_DIR / "TLEM2_CT_tibia_r.stl"
VOXEL_MM = 1.0


@dataclass(frozen=True)
class FusedMesh:
    vertices: np.ndarray  # (n, 3) world mm, the source's frame
    faces: np.ndarray  # (m, 3), outward
    contact_z_mm: np.ndarray  # world z of the voxels where the tibia's part of the mask touches the fibula's
    tibia_top_z_mm: float  # highest point of the source tibia
    fibula_bottom_z_mm: float  # lowest point of the source fibula (the lateral malleolus)
    source_volume_mm3: float  # tibia + fibula of the source
    seconds: float  # time to build


def build_fused(source: Path = SOURCE, voxel_mm: float = VOXEL_MM) -> FusedMesh:
    """Voxelise both bodies of ``source`` on one grid, threshold at half occupancy, mesh the mask."""
    import trimesh
    from scipy import ndimage
    from skimage.measure import marching_cubes

    from bonecad.imaging.voxelize import occupancy

    start = time.perf_counter()
    mesh = trimesh.load(source, force="mesh")
    bodies = sorted(mesh.split(only_watertight=False), key=lambda b: abs(b.volume))
    if len(bodies) != 2:
        raise ValueError(f"{source}: expected a tibia and a fibula, found {len(bodies)} bodies")
    fibula, tibia = bodies
    origin = mesh.vertices.min(axis=0) - 2.0 * voxel_mm
    shape = tuple(int(n) for n in np.ceil((mesh.vertices.max(axis=0) - origin) / voxel_mm)[::-1] + 3)
    # the bodies are disjoint, so the occupancy of both is the sum of each one's
    occ_tibia = occupancy(tibia.vertices, tibia.faces, origin, voxel_mm, shape)
    occ_fibula = occupancy(fibula.vertices, fibula.faces, origin, voxel_mm, shape)
    mask = (occ_tibia + occ_fibula) >= 0.5
    # where the two bones meet in the mask: a tibia voxel 6-adjacent to a fibula voxel
    tibia_part, fibula_part = mask & (occ_tibia >= occ_fibula), mask & (occ_fibula > occ_tibia)
    contact = tibia_part & ndimage.binary_dilation(fibula_part)
    contact_z = np.unique(np.nonzero(contact)[0]) * voxel_mm + origin[2]
    grid_vertices, faces, _, _ = marching_cubes(mask.astype(np.float32), 0.5, allow_degenerate=False)
    vertices = grid_vertices[:, ::-1].astype(np.float64) * voxel_mm + origin
    return FusedMesh(
        vertices=vertices,
        faces=faces.astype(np.int64),
        contact_z_mm=contact_z,
        tibia_top_z_mm=float(tibia.vertices[:, 2].max()),
        fibula_bottom_z_mm=float(fibula.vertices[:, 2].min()),
        source_volume_mm3=float(abs(tibia.volume) + abs(fibula.volume)),
        seconds=time.perf_counter() - start,
    )


def fuse_meshes(meshes, voxel_mm: float = VOXEL_MM) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces (world mm) of the union of ``meshes`` (trimesh, disjoint) voxelised on one grid and
    thresholded at half occupancy, as a CT threshold would: bones closer than about a voxel join."""
    from skimage.measure import marching_cubes

    from bonecad.imaging.voxelize import occupancy

    points = np.vstack([m.vertices for m in meshes])
    origin = points.min(axis=0) - 2.0 * voxel_mm
    shape = tuple(int(n) for n in np.ceil((points.max(axis=0) - origin) / voxel_mm)[::-1] + 3)
    occ = sum(occupancy(m.vertices, m.faces, origin, voxel_mm, shape) for m in meshes)
    grid_vertices, faces, _, _ = marching_cubes((occ >= 0.5).astype(np.float32), 0.5, allow_degenerate=False)
    return grid_vertices[:, ::-1].astype(np.float64) * voxel_mm + origin, faces.astype(np.int64)


def write_fused(path: Path, fused: FusedMesh) -> Path:
    import trimesh

    trimesh.Trimesh(fused.vertices, fused.faces, process=False).export(path)
    return path


if __name__ == "__main__":  # pragma: no cover - by hand
    fused = build_fused()
    out = write_fused(Path(sys.argv[1] if len(sys.argv) > 1 else "TLEM2_fused_1mm.stl"), fused)
    print(f"{out}: {len(fused.faces)} triangles in {fused.seconds:.2f} s; the bones touch at z "
          f"{fused.contact_z_mm.min():.1f}..{fused.contact_z_mm.max():.1f} mm "
          f"(tibia top {fused.tibia_top_z_mm:.1f} mm)")
