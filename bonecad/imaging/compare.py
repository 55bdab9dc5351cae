"""Surface-to-surface distance for checking a segmentation against the mesh it came from; the
voxel staircase a segmentation without sub-voxel interpolation makes of a smooth bone."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bonecad.settings import ImagingSettings, MeshSettings


@dataclass(frozen=True)
class SurfaceDistance:
    """Symmetric point-to-surface distances between two meshes, mm."""

    rms_mm: float  # RMS over samples of both surfaces
    mean_mm: float
    max_mm: float  # largest sampled distance, either way
    centroid_shift_mm: float  # distance between the two volume centroids


def surface_distance(a, b, *, samples: int = 20000, seed: int = 0) -> SurfaceDistance:
    """Distances between trimesh meshes ``a`` and ``b``: area-uniform samples of each, nearest points on the other."""
    import trimesh

    rng = np.random.default_rng(seed)
    distances = []
    for source, target in ((a, b), (b, a)):
        points, _ = trimesh.sample.sample_surface(source, samples, seed=int(rng.integers(1 << 31)))
        distances.append(distance_to_surface(target, points))
    d = np.concatenate(distances)
    return SurfaceDistance(
        rms_mm=float(np.sqrt(np.mean(d**2))),
        mean_mm=float(d.mean()),
        max_mm=float(d.max()),
        centroid_shift_mm=float(np.linalg.norm(a.center_mass - b.center_mass)),
    )


def distance_to_surface(mesh, points: np.ndarray) -> np.ndarray:
    """(n,) exact distance (mm) from each of (n, 3) ``points`` to trimesh ``mesh``."""
    from bonecad.mesh.closest import TriangleLocator

    return TriangleLocator(mesh.vertices, mesh.faces).query(points).distance


def staircase_mesh(vertices: np.ndarray, faces: np.ndarray, voxel_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The voxel staircase of a closed mesh: marching cubes of its binary mask on a ``voxel_mm`` grid.

    This is what a segmentation without sub-voxel interpolation gives (the JIA
    MRI tibia: vertices on a half-voxel lattice), with the smooth surface it
    came from known. Returns (vertices (n, 3) mm, faces (m, 3)), outward.
    """
    from skimage.measure import marching_cubes

    from bonecad.imaging.voxelize import occupancy

    vertices = np.asarray(vertices, dtype=np.float64)
    origin = vertices.min(axis=0) - 2.0 * voxel_mm
    nz, ny, nx = (int(n) for n in np.ceil((vertices.max(axis=0) - origin) / voxel_mm)[::-1] + 3)
    mask = occupancy(vertices, faces, origin, voxel_mm, (nz, ny, nx)) >= 0.5
    grid_vertices, grid_faces, _, _ = marching_cubes(mask.astype(np.float32), 0.5, allow_degenerate=False)
    return grid_vertices[:, ::-1] * voxel_mm + origin, grid_faces.astype(np.int64)


def largest_body(mesh):
    """The body of trimesh ``mesh`` enclosing the most volume (the tibia of a tibia + fibula mesh)."""
    bodies = mesh.split(only_watertight=False)
    if len(bodies) <= 1:
        return mesh
    return max(bodies, key=lambda m: abs(m.volume))


@dataclass(frozen=True)
class RoundTrip:
    """Mesh -> synthetic CT -> segmented mesh, against the mesh's largest body."""

    distance: SurfaceDistance
    segmented: object  # BoneMesh
    ct_shape: tuple[int, int, int]  # (nk, nj, ni) voxels
    phantom_seconds: float
    segment_seconds: float


def round_trip(mesh, *, settings: ImagingSettings, mesh_settings: MeshSettings, voxel_mm: float = 0.5,
               noise_hu: float = 30.0, seed: int = 0) -> RoundTrip:
    """Synthetic CT of trimesh ``mesh`` (``voxel_mm`` mm, ``noise_hu`` HU noise), segmented (``settings``: the
    [imaging] section, ``mesh_settings`` the [mesh] one), compared with its tibia."""
    import time

    from bonecad.imaging.phantom import mesh_to_ct
    from bonecad.imaging.segment import segment_bone

    start = time.perf_counter()
    ct = mesh_to_ct(mesh.vertices, mesh.faces, voxel_mm=voxel_mm, noise_hu=noise_hu, seed=seed)
    middle = time.perf_counter()
    segmented = segment_bone(ct, settings=settings, mesh_settings=mesh_settings)
    end = time.perf_counter()
    distance = surface_distance(segmented.to_trimesh(), largest_body(mesh), seed=seed)
    return RoundTrip(distance, segmented, ct.shape, middle - start, end - middle)
