"""The bodies of a broken long bone by anatomy: its main fragments, intermediate ones, neighbours and specks.

A broken tibia or femur arrives as several closed bodies (a segmentation of the fracture). The rules, on the
cleaned bodies of ``mesh.intake`` (lengths mm, volumes mm^3):

- a thin long body (``[mesh] thin_body_slenderness``) is the fibula (a neighbour);
- bodies smaller than ``[fracture] speck_volume_share`` of the rest are specks: dropped and reported;
- the two largest of the rest are the main fragments; their joint long axis points to the proximal end (a
  tibia's wider end, a femur's narrower one: ``mesh.bodies.proximal_direction``), and the one further along
  it is the proximal fragment;
- a body whose centre lies beyond the main fragments' ends is a neighbour: beyond a tibia's proximal end the
  femur (long) or the patella, beyond its distal end the talus; beyond a femur's distal end the tibia (long)
  or the patella;
- the others are intermediate (butterfly) fragments.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bonecad.errors import InputError
from bonecad.mesh.bodies import body_shape, proximal_direction
from bonecad.mesh.intake import Kept, Units, _bodies, _clean, _detect_scale, _repaired, read_mesh_file
from bonecad.settings import FractureSettings, MeshSettings, UnitsSettings


@dataclass(frozen=True)
class Piece:
    """One body of a broken bone's mesh: vertices (mm), faces (outward), its role ("proximal", "distal",
    "intermediate" fragment, or a neighbour: "fibula", "patella", "talus", "femur", "tibia"), volume (mm^3),
    length (mm), centroid (mm) and, for a main fragment, which end of the bone it carries."""

    vertices: np.ndarray
    faces: np.ndarray
    role: str
    volume_mm3: float
    length_mm: float
    centroid: np.ndarray
    carries: str = ""


@dataclass(frozen=True)
class BrokenBone:
    """A broken bone's mesh read: the fragments (proximal, distal, then intermediate by volume), the
    neighbours, the specks dropped (descriptions), the long axis (unit, proximal), the repairs, the source."""

    fragments: tuple[Piece, ...]
    neighbours: tuple[Piece, ...]
    specks: tuple[str, ...]
    up: np.ndarray
    repairs: tuple[str, ...]
    source: str

    def describe(self) -> str:
        """One line per body, for the log and the report."""
        lines = [f"{p.role} fragment: {p.length_mm:.0f} mm, {p.volume_mm3 / 1000:.1f} cm3"
                 + (f" (carries the {p.carries} end)" if p.carries else "") for p in self.fragments]
        lines += [f"{p.role} (neighbour): {p.length_mm:.0f} mm, {p.volume_mm3 / 1000:.1f} cm3"
                  for p in self.neighbours]
        lines += [f"dropped speck: {s}" for s in self.specks]
        return "\n".join(lines)


def load_broken_bone(path: str | Path, *, units: Units = "auto", settings: MeshSettings, plausible: UnitsSettings,
                     fracture: FractureSettings, bone: Kept = "tibia") -> BrokenBone:
    """Read and clean a mesh of a broken bone and name its bodies (module docstring).

    Raises InputError naming the file when it holds fewer than two fragments (nothing to reduce)."""
    source = Path(path)
    vertices, faces = read_mesh_file(source)
    cleaned = _clean(vertices, faces)
    if not cleaned.manifold():
        cleaned = _repaired(vertices, faces, settings.max_hole_edges)
    bodies = _bodies(cleaned)
    if not bodies or bodies[0].volume <= 0:
        raise InputError("has no closed body with a volume", source)
    shapes = [body_shape(b.vertices, b.volume, b.centroid) for b in bodies]
    scale = _detect_scale(max(s.length for s in shapes), shapes[0].width, units, source, plausible.tibia_length_mm)
    pieces = [Piece(b.vertices * scale, b.faces, "", s.volume * scale**3, s.length * scale, s.centroid * scale)
              for b, s in zip(bodies, shapes)]
    thin = [s.slenderness >= settings.thin_body_slenderness for s in shapes]
    rest = [p for p, t in zip(pieces, thin) if not t]
    neighbours = [_named(p, "fibula") for p, t in zip(pieces, thin) if t]
    total = sum(p.volume_mm3 for p in rest)
    specks = [p for p in rest if p.volume_mm3 < fracture.speck_volume_share * total]
    rest = [p for p in rest if p.volume_mm3 >= fracture.speck_volume_share * total]
    if len(rest) < 2:
        raise InputError(f"holds {len(rest)} bone fragment(s) larger than {100 * fracture.speck_volume_share:g} % "
                         "of the bone: nothing to reduce (bonecad reconstruct models an intact bone)", source)
    a, b = rest[0], rest[1]  # the two largest
    both_v = np.concatenate([a.vertices, b.vertices])
    both_f = np.concatenate([a.faces, b.faces + len(a.vertices)])
    centre = both_v.mean(axis=0)
    axis = b.centroid - a.centroid
    axis /= np.linalg.norm(axis)
    up = proximal_direction(both_v, both_f, centre, axis)
    if bone == "femur":
        up = -up
    proximal, distal = (a, b) if (a.centroid - b.centroid) @ up > 0 else (b, a)
    heights = both_v @ up
    low, high = float(heights.min()), float(heights.max())
    fragments = [_named(proximal, "proximal", "proximal"), _named(distal, "distal", "distal")]
    for p in rest[2:]:
        h = float(p.centroid @ up)
        if h > high:
            neighbours.append(_named(p, ("tibia" if bone == "femur" else "femur") if _long(p, settings)
                                     else "patella" if bone == "tibia" else "pelvis"))
        elif h < low:
            neighbours.append(_named(p, ("tibia" if _long(p, settings) else "patella") if bone == "femur"
                                     else "talus"))
        else:
            fragments.append(_named(p, "intermediate"))
    return BrokenBone(tuple(fragments), tuple(neighbours),
                      tuple(f"{p.volume_mm3:.0f} mm3, {p.length_mm:.1f} mm" for p in specks), up,
                      tuple(cleaned.repairs) + ((f"scaled by {scale:g} to mm (--units {units})",) if scale != 1
                                                else ()),
                      str(source))


def _long(piece: Piece, settings: MeshSettings) -> bool:
    """Whether a body is a long bone (slender)."""
    return body_shape(piece.vertices, piece.volume_mm3, piece.centroid).slenderness >= settings.long_body_slenderness


def _named(piece: Piece, role: str, carries: str = "") -> Piece:
    return Piece(piece.vertices, piece.faces, role, piece.volume_mm3, piece.length_mm, piece.centroid, carries)
