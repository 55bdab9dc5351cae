"""Synthetic fractures of a closed long-bone mesh: cut, close, displace (the ground truth for reduction).

A fracture surface is a height field over the bone's cross-section, in the bone's axial frame (``axial_frame``):
flat (transverse), a tilted plane (oblique) or one turn of a helix whose ends are joined by a steep longitudinal
limb (spiral, the classic torsion fracture). The surface closes a large solid below it (the cutter); exact mesh
booleans (manifold3d) give the distal fragment (bone and cutter) and the proximal one (bone less cutter), each a
closed manifold whose faces remember whether they are the bone's surface or the cut's. An optional butterfly
wedge (a triangular prism through one side of the shaft, sized to a share of the bone's volume) is cut out
first. Each fragment is then moved by a seeded rigid displacement (the proximal fragment stays; the distal one
turns by up to ``rotation_deg`` about a random axis through the fracture's centre, moves by ``translation_mm``
across the axis and by ``shortening_mm`` along it towards the proximal end).

Lengths in mm, angles in degrees. ``Fragment.displacement`` (4 x 4) maps the fragment's place in the intact bone
to its displaced place: the truth a reduction must undo.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from bonecad.mesh.bodies import body_shape, proximal_direction
from bonecad.mesh.sections import plane_basis

FractureKind = Literal["transverse", "oblique", "spiral"]
FRACTURE_KINDS: tuple[str, ...] = ("transverse", "oblique", "spiral")
BoneKind = Literal["tibia", "femur"]


@dataclass(frozen=True)
class AxialFrame:
    """A bone's long axis: ``up`` (unit, towards the proximal end), ``u``/``v`` across it, ``centre`` (mm),
    the heights of the distal and proximal ends along ``up`` from ``centre`` (mm)."""

    centre: np.ndarray
    up: np.ndarray
    u: np.ndarray
    v: np.ndarray
    bottom: float
    top: float

    @property
    def length(self) -> float:
        return self.top - self.bottom

    def height(self, points: np.ndarray) -> np.ndarray:
        """(n,) mm from the distal end along the axis."""
        return (np.asarray(points) - self.centre) @ self.up - self.bottom


def axial_frame(vertices: np.ndarray, faces: np.ndarray, bone: BoneKind = "tibia") -> AxialFrame:
    """The long axis of a closed bone mesh (principal axis) pointing to its proximal end: a tibia's wider end
    (the plateau), a femur's narrower one (its head; the condyles are the wider end)."""
    centre = vertices.mean(axis=0)
    axis = body_shape(vertices, 0.0, centre).axis
    up = proximal_direction(vertices, faces, centre, axis)
    if bone == "femur":
        up = -up
    u, v = plane_basis(up)
    heights = (vertices - centre) @ up
    return AxialFrame(centre, up, u, v, float(heights.min()), float(heights.max()))


@dataclass(frozen=True)
class Fragment:
    """One closed fragment as displaced: vertices (mm), faces (outward), ``fracture`` (m,) bool the faces of the
    fracture surface (the rest are the bone's own surface), its role ("proximal", "distal", "butterfly") and
    ``displacement`` (4 x 4) from its place in the intact bone to where it is."""

    vertices: np.ndarray
    faces: np.ndarray
    fracture: np.ndarray
    role: str
    displacement: np.ndarray

    @property
    def intact_vertices(self) -> np.ndarray:
        """The vertices at their place in the intact bone (mm)."""
        return apply(np.linalg.inv(self.displacement), self.vertices)


@dataclass(frozen=True)
class Fracture:
    """A fractured bone: the intact bone (vertices, faces), its axial frame, the fracture kind, the fracture
    line's height above the distal end (mm, at the shaft's centre), the butterfly's share of the bone's volume
    (0 without one) and the displaced fragments, proximal first."""

    intact_vertices: np.ndarray
    intact_faces: np.ndarray
    frame: AxialFrame
    kind: str
    level_mm: float
    butterfly_share: float
    fragments: tuple[Fragment, ...]

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """All fragments as one mesh (vertices, faces), as a segmentation of the fracture gives them."""
        return combine([(f.vertices, f.faces) for f in self.fragments])


def apply(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (n, 3) moved by a 4 x 4 rigid transform."""
    return np.asarray(points) @ transform[:3, :3].T + transform[:3, 3]


def combine(meshes: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Several meshes as one (vertices, faces)."""
    offsets = np.cumsum([0] + [len(v) for v, _ in meshes[:-1]])
    return (np.concatenate([v for v, _ in meshes]),
            np.concatenate([f + o for (_, f), o in zip(meshes, offsets)]))


def rotation(axis: np.ndarray, degrees: float) -> np.ndarray:
    """3 x 3 rotation by ``degrees`` about the unit ``axis`` (Rodrigues)."""
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.radians(degrees)
    return np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * (k @ k)


def rigid(rot: np.ndarray, pivot: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """4 x 4: rotate by ``rot`` about ``pivot``, then translate by ``shift`` (mm)."""
    t = np.eye(4)
    t[:3, :3] = rot
    t[:3, 3] = pivot - rot @ pivot + shift
    return t


def _manifold(vertices: np.ndarray, faces: np.ndarray):
    """A manifold3d solid of a closed mesh, its triangles tagged as one original mesh."""
    import manifold3d

    mesh = manifold3d.Mesh(vert_properties=np.asarray(vertices, dtype=np.float32),
                           tri_verts=np.asarray(faces, dtype=np.uint32))
    solid = manifold3d.Manifold(mesh)
    if solid.status() != manifold3d.Error.NoError:
        raise ValueError(f"the mesh is not a closed manifold ({solid.status()})")
    return solid.as_original()


def _pieces(solid, bone_id: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The connected pieces of a manifold3d result: (vertices, faces, fracture mask), largest volume first; a
    face is of the fracture when it does not come from the bone (original id ``bone_id``)."""
    out = []
    for piece in solid.decompose():
        mesh = piece.to_mesh()
        faces = np.asarray(mesh.tri_verts, dtype=np.int64)
        ids = np.asarray(mesh.run_original_id)
        runs = np.asarray(mesh.run_index)
        per_face = np.repeat(ids, np.diff(runs) // 3)
        out.append((np.asarray(mesh.vert_properties[:, :3], dtype=np.float64), faces, per_face != bone_id,
                    float(piece.volume())))
    out.sort(key=lambda p: -p[3])
    return [p[:3] for p in out]


def _height_field(kind: str, radius: np.ndarray, angle: np.ndarray, width: float, obliquity_deg: float,
                  spiral_pitch: float) -> np.ndarray:
    """The fracture surface's height (mm) above the fracture level at (radius mm, angle rad) across the axis.

    The spiral rises by ``spiral_pitch`` over all but 12 degrees of the turn and falls back over those (its
    longitudinal limb); within 2 mm of the axis its height shrinks to the level (one point on the axis)."""
    if kind == "transverse":
        return np.zeros_like(radius)
    if kind == "oblique":
        return np.tan(np.radians(obliquity_deg)) * radius * np.cos(angle)
    if kind == "spiral":
        limb = np.radians(12.0)
        turn = np.mod(angle, 2 * np.pi)
        share = np.where(turn < 2 * np.pi - limb, turn / (2 * np.pi - limb), (2 * np.pi - turn) / limb)
        return np.minimum(1.0, radius / 2.0) * spiral_pitch * (share - 0.5)
    raise ValueError(f"unknown fracture kind '{kind}' (one of {', '.join(FRACTURE_KINDS)})")


def _cutter(frame: AxialFrame, centre: np.ndarray, kind: str, reach: float, obliquity_deg: float,
            spiral_pitch: float, depth: float) -> tuple[np.ndarray, np.ndarray]:
    """A closed solid (vertices, faces) whose top is the fracture surface about ``centre`` (a point on the
    axis at the level), reaching ``reach`` mm across the axis and ``depth`` mm down it."""
    if kind == "spiral":  # (a plane is exact on any triangulation; a helix needs 1.5 degrees and fine rings)
        radii = np.r_[0.0, np.linspace(0.5, 2.0, 4), np.geomspace(3.0, reach, 24)]
        angles = np.linspace(0.0, 2 * np.pi, 240, endpoint=False)
    else:
        radii = np.array([0.0, reach])
        angles = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
    rr, aa = np.meshgrid(radii[1:], angles, indexing="ij")  # (rings, angles)
    h = _height_field(kind, rr, aa, reach, obliquity_deg, spiral_pitch)
    ring_points = (centre + rr[..., None] * (np.cos(aa)[..., None] * frame.u + np.sin(aa)[..., None] * frame.v)
                   + h[..., None] * frame.up)
    n_rings, n_angles = rr.shape
    top = ring_points.reshape(-1, 3)
    outer_ring = top[-n_angles:]
    bottom = outer_ring - (((outer_ring - centre) @ frame.up) + depth)[:, None] * frame.up
    vertices = np.concatenate([centre[None], top, bottom, (centre - depth * frame.up)[None]])
    j = np.arange(n_angles)
    jn = (j + 1) % n_angles
    ring = lambda i, k: 1 + i * n_angles + k  # noqa: E731
    faces = [np.stack([np.zeros(n_angles, dtype=np.int64), ring(0, j), ring(0, jn)], axis=1)]  # centre fan
    for i in range(n_rings - 1):
        faces += [np.stack([ring(i, j), ring(i + 1, j), ring(i + 1, jn)], axis=1),
                  np.stack([ring(i, j), ring(i + 1, jn), ring(i, jn)], axis=1)]
    b0 = 1 + n_rings * n_angles
    outer = ring(n_rings - 1, j)
    faces += [np.stack([outer, b0 + j, b0 + jn], axis=1), np.stack([outer, b0 + jn, outer - j + jn], axis=1)]
    last = len(vertices) - 1
    faces += [np.stack([np.full(n_angles, last), b0 + jn, b0 + j], axis=1)]  # bottom fan
    return vertices, _outward(vertices, np.concatenate(faces))


def _outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``faces`` of a closed mesh turned, if need be, so that its volume is positive (normals outward)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return faces if np.einsum("ij,ij->i", a, np.cross(b, c)).sum() > 0 else faces[:, ::-1].copy()


def _shaft_centre(vertices: np.ndarray, frame: AxialFrame, level: float) -> np.ndarray:
    """The point on the bone's axis at height ``level`` (mm above the distal end), moved to the mean of the
    vertices within 3 mm of that height (the shaft's own centre where the bone bows)."""
    heights = frame.height(vertices)
    near = np.abs(heights - level) < 3.0
    on_axis = frame.centre + (frame.bottom + level) * frame.up
    if near.sum() < 10:
        return on_axis
    mean = vertices[near].mean(axis=0)
    return mean - ((mean - on_axis) @ frame.up) * frame.up


def _wedge(frame: AxialFrame, centre: np.ndarray, side: float, span: float, depth: float, width: float,
           reach: float) -> tuple[np.ndarray, np.ndarray]:
    """A triangular prism (vertices, faces): its base ``span`` mm long along the axis outside the bone on the
    side at angle ``side`` (rad), its apex ``depth`` mm from the bone's outside towards the axis, ``width`` mm
    thick across."""
    out = np.cos(side) * frame.u + np.sin(side) * frame.v
    across = np.cross(frame.up, out)
    base = centre + reach * out
    apex = centre + (reach - depth) * out
    tri = np.array([base + 0.5 * span * frame.up, base - 0.5 * span * frame.up, apex])
    vertices = np.concatenate([tri - 0.5 * width * across, tri + 0.5 * width * across])
    faces = np.array([[0, 2, 1], [3, 4, 5], [0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [2, 0, 3], [2, 3, 5]])
    return vertices, _outward(vertices, faces)


def fracture_bone(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    kind: str = "transverse",
    bone: BoneKind = "tibia",
    level_share: float = 0.5,
    obliquity_deg: float = 35.0,
    spiral_pitch_share: float = 0.25,
    butterfly_share: float = 0.0,
    rotation_deg: float = 15.0,
    translation_mm: float = 8.0,
    shortening_mm: float = 0.0,
    seed: int = 0,
) -> Fracture:
    """A closed bone mesh broken and displaced (see the module docstring).

    level_share : the fracture's height above the distal end, a share of the bone's length
    obliquity_deg : an oblique fracture's angle to the cross-section
    spiral_pitch_share : a spiral's rise over its turn, a share of the bone's length
    butterfly_share : a butterfly wedge's share of the bone's volume (0: none; 0.02-0.04 is typical)
    rotation_deg, translation_mm, shortening_mm : the distal fragment's displacement (the butterfly moves by a
        fifth of each, its own seeded way)

    Raises ValueError for a mesh that is not a closed manifold or a cut that does not split it in two.
    """
    import manifold3d

    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if kind not in FRACTURE_KINDS:
        raise ValueError(f"unknown fracture kind '{kind}' (one of {', '.join(FRACTURE_KINDS)})")
    frame = axial_frame(vertices, faces, bone)
    level = level_share * frame.length
    centre = _shaft_centre(vertices, frame, level)
    across = vertices - frame.centre
    reach = 1.5 * float(np.linalg.norm(across - np.outer(across @ frame.up, frame.up), axis=1).max()) + 10.0
    solid = _manifold(vertices, faces)
    bone_id = solid.original_id()
    cutter = _manifold(*_cutter(frame, centre, kind, reach, obliquity_deg, spiral_pitch_share * frame.length,
                                2.0 * frame.length))
    rng = np.random.default_rng(seed)
    pieces: list[tuple[str, object]] = []
    rest = solid
    if butterfly_share > 0:
        near = np.abs(frame.height(vertices) - level) < 5.0
        radial = np.linalg.norm(across[near] - np.outer(across[near] @ frame.up, frame.up), axis=1)
        outer = float(radial.max())
        side = float(rng.uniform(0, 2 * np.pi))
        target = butterfly_share * solid.volume()
        scale_lo, scale_hi = 0.05, 1.5
        wedge = None
        for _ in range(30):  # the wedge's size by bisection on its share of the volume
            scale = 0.5 * (scale_lo + scale_hi)
            prism = _manifold(*_wedge(frame, centre, side, 2.5 * outer * scale + 5.0, outer * scale + (reach - outer),
                                      2.0 * outer * min(1.0, 0.5 + scale), reach))
            wedge = solid ^ prism
            volume = wedge.volume()
            if abs(volume - target) < 0.02 * target:
                break
            scale_lo, scale_hi = (scale, scale_hi) if volume < target else (scale_lo, scale)
        assert wedge is not None
        pieces.append(("butterfly", wedge))
        rest = solid - prism
    distal, proximal = rest ^ cutter, rest - cutter
    parts = []
    for role, piece in (("proximal", proximal), ("distal", distal), *pieces):
        found = _pieces(piece, bone_id)
        if not found:
            raise ValueError(f"the {kind} cut leaves no {role} fragment")
        small = [p for p in found[1:] if len(p[1])]
        if small and role != "butterfly":
            volumes = [abs(manifold3d.Manifold(manifold3d.Mesh(vert_properties=p[0].astype(np.float32),
                                                                 tri_verts=p[1].astype(np.uint32))).volume())
                       for p in small]
            if max(volumes) > 0.01 * solid.volume():
                raise ValueError(f"the {kind} cut splits the {role} side into {len(found)} pieces")
        parts.append((role, found[0]))
    fragments = []
    max_pivot = centre
    for role, (v, f, fracture) in parts:
        if role == "proximal":
            move = np.eye(4)
        else:
            share = 1.0 if role == "distal" else 0.2
            axis = rng.normal(size=3)
            turn = rotation(axis, share * rotation_deg)
            direction = rng.normal(size=3)
            direction -= (direction @ frame.up) * frame.up
            direction /= np.linalg.norm(direction)
            shift = share * (translation_mm * direction + shortening_mm * frame.up)
            move = rigid(turn, max_pivot if role == "distal" else v.mean(axis=0), shift)
        fragments.append(Fragment(apply(move, v), f, fracture, role, move))
    return Fracture(vertices, faces, frame, kind, float(level), float(butterfly_share), tuple(fragments))


def fracture_ct(fracture: Fracture, *, voxel_mm: tuple[float, float, float] = (0.8, 0.8, 1.0), noise_hu: float = 30.0,
                seed: int = 0):
    """The displaced fragments imaged as a synthetic CT (``phantom.mesh_to_ct``: cortical shell, marrow, soft
    tissue, blur, noise) on a clinical grid (in-plane pixel, slice spacing, mm). Fragments that overlap as
    displaced (a large shortening) image as one body, as they would."""
    from bonecad.imaging.phantom import mesh_to_ct

    return mesh_to_ct(*fracture.mesh(), voxel_mm=voxel_mm, noise_hu=noise_hu, seed=seed)
