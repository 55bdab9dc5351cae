"""Whole legs from the bone sets of ../shared/data: the tibia (with its fibula where the mesh holds one),
femur, patella and talus of one subject, in their common scanner coordinates, and synthetic CTs of them.

The two MRI legs (ICL: 2.6 mm facets; JIA: a 1 mm voxel staircase) are
smoothed before they are imaged: a CT images a bone, not the facets or the
staircase of another scan's segmentation, against which no smooth surface
scores (JIA's own true surface is within 0.25 mm of 80 % of its staircase).
Every bone of such a leg gets the same Taubin smoothing (no shrinkage), and
the smoothed tibia is the truth the reconstruction is measured against.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .conftest import DATA

#: subject -> (files under ../shared/data, side as the data README states it, smoothed before imaging)
LEGS: dict[str, tuple[tuple[str, ...], str, bool]] = {
    "LHDL": (("tibia/LHDL_CT_tibia_r.stl", "femur/LHDL_CT_femur_r.stl", "leg/LHDL_CT_patella_r.stl",
              "leg/LHDL_CT_talus_r.stl"), "right", False),
    "TLEM2": (("tibia/TLEM2_CT_tibia_r.stl", "femur/TLEM2_CT_femur_r.stl", "leg/TLEM2_CT_patella_r.stl",
               "leg/TLEM2_CT_talus_r.stl"), "right", False),
    "ICL": (("tibia/ICL_MRI_tibia_r.stl", "femur/ICL_MRI_femur_r.stl", "leg/ICL_MRI_patella_r.stl",
             "leg/ICL_MRI_talus_r.stl"), "right", True),
    "JIA": (("tibia/JIA_MRI_tibia_l.stl", "femur/JIA_MRI_femur_l.stl", "leg/JIA_MRI_patella_l.stl",
             "leg/JIA_MRI_talus_l.stl"), "left", True),
}
#: Taubin smoothing of the MRI legs (lambda 0.5, mu -0.53), after one subdivision of ICL's coarse facets
SMOOTHING_ITERATIONS = 20


@dataclass(frozen=True)
class Leg:
    """All bodies of one leg (vertices mm, faces) and the true tibia (the largest body of the tibia file)."""

    subject: str
    side: str
    vertices: np.ndarray
    faces: np.ndarray
    tibia_vertices: np.ndarray
    tibia_faces: np.ndarray


def leg_files_present(subject: str) -> bool:
    return all((DATA / name).is_file() for name in LEGS[subject][0])


def load_leg(subject: str) -> Leg:
    """The bodies of ``subject``'s leg, smoothed where its data is an MRI segmentation."""
    import trimesh

    names, side, smooth = LEGS[subject]
    bodies = []
    for name in names:
        mesh = trimesh.load(DATA / name, force="mesh")
        for body in mesh.split(only_watertight=False):
            if smooth:
                if np.median(body.edges_unique_length) > 2.0:
                    body = body.subdivide()
                trimesh.smoothing.filter_taubin(body, lamb=0.5, nu=0.53, iterations=SMOOTHING_ITERATIONS)
            bodies.append(body)
        if name == names[0]:
            tibia = max(bodies, key=lambda b: abs(b.volume))  # the tibia file's largest body
    offsets = np.cumsum([0] + [len(b.vertices) for b in bodies[:-1]])
    return Leg(
        subject=subject,
        side=side,
        vertices=np.vstack([b.vertices for b in bodies]),
        faces=np.vstack([b.faces + o for b, o in zip(bodies, offsets)]),
        tibia_vertices=np.asarray(tibia.vertices),
        tibia_faces=np.asarray(tibia.faces),
    )


def leg_ct(leg: Leg, voxel_mm: tuple[float, float, float], *, noise_hu: float = 30.0, seed: int = 0):
    """A synthetic CT of the whole leg (``bonecad.imaging.mesh_to_ct``): cortex, marrow, soft tissue, air,
    0.4 mm blur, ``noise_hu`` noise, slices as thick as their spacing."""
    from bonecad.imaging import mesh_to_ct

    return mesh_to_ct(leg.vertices, leg.faces, voxel_mm=voxel_mm, noise_hu=noise_hu, seed=seed)
