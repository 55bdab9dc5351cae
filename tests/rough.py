"""A rough segmentation made from a real tibia, with the clean surface it came from known.

TLEM2's CT tibia (1 mm edges) gets smooth random bumps: Gaussian bumps of
1.5-3 mm radius (about a clinical MRI's voxel) at 3000 random places of the
surface, summed and scaled so the largest displacement along the normal is
1 mm, then a coarse quadric decimation (``fast_simplification`` through
trimesh) to about 1.8 mm edges, which on the nearly straight shaft leaves
slivers along the axis (up to 13 mm). Deterministic (fixed seeds).

``python -m tests.rough OUT.stl`` writes the mesh.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .conftest import TIBIA_DIR

SOURCE = TIBIA_DIR / "TLEM2_CT_tibia_r.stl"
BUMPS, BUMP_RADIUS_MM, MAX_BUMP_MM = 3000, (1.5, 3.0), 1.0
FACES = 24000


@dataclass(frozen=True)
class RoughMesh:
    vertices: np.ndarray
    faces: np.ndarray
    clean_vertices: np.ndarray  # the tibia before bumps and decimation
    clean_faces: np.ndarray
    median_edge_mm: float
    max_edge_mm: float


def build_rough(source: Path = SOURCE, faces: int = FACES, seed: int = 0, bumps: int = BUMPS,
                bump_radius_mm: tuple[float, float] = BUMP_RADIUS_MM) -> RoughMesh:
    import trimesh
    from scipy.spatial import cKDTree

    clean = max(trimesh.load(source, force="mesh").split(only_watertight=False), key=lambda b: abs(b.volume))
    rng = np.random.default_rng(seed)
    centres, _ = trimesh.sample.sample_surface(clean, bumps, seed=seed + 1)
    sign = rng.choice([-1.0, 1.0], bumps)
    amplitude = rng.uniform(0.5, 1.0, bumps) * sign
    radius = rng.uniform(*bump_radius_mm, bumps)
    # sum of Gaussian bumps at every vertex: (vertex, bump) pairs within 3 radii
    pairs = cKDTree(centres).sparse_distance_matrix(cKDTree(clean.vertices), 3 * max(bump_radius_mm),
                                                    output_type="coo_matrix")
    bump, vertex, distance = pairs.row, pairs.col, pairs.data
    field = np.bincount(vertex, weights=amplitude[bump] * np.exp(-0.5 * (distance / radius[bump]) ** 2),
                        minlength=len(clean.vertices))
    field *= MAX_BUMP_MM / np.abs(field).max()
    bumpy = trimesh.Trimesh(clean.vertices + clean.vertex_normals * field[:, None], clean.faces, process=False)
    rough = bumpy.simplify_quadric_decimation(face_count=faces)
    rough.merge_vertices()
    trimesh.repair.fill_holes(rough)
    edges = rough.edges_unique_length
    return RoughMesh(np.asarray(rough.vertices), np.asarray(rough.faces), np.asarray(clean.vertices),
                     np.asarray(clean.faces), float(np.median(edges)), float(edges.max()))


if __name__ == "__main__":  # pragma: no cover - by hand
    import trimesh

    rough = build_rough()
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "TLEM2_rough.stl")
    trimesh.Trimesh(rough.vertices, rough.faces, process=False).export(out)
    print(f"{out}: {len(rough.faces)} triangles, median edge {rough.median_edge_mm:.2f} mm, "
          f"longest {rough.max_edge_mm:.1f} mm")
