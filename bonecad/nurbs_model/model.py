"""The NURBS baseline model (DESIGN.md step 4), built from the contour curves.

::

    contours = contour_curves(bone, frame, settings=settings.curves)
    model = build_nurbs(contours, settings=settings.nurbs)
    model.solid            # build123d Solid, scanner mm
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from bonecad.contours.curves import ContourSet
from bonecad.errors import KernelError
from bonecad.occ import brep
from bonecad.occ.pickling import ShapePickling
from bonecad.occ import surfaces as occ
from bonecad.occ.interop import to_build123d
from bonecad.nurbs_model.loft import BoneSurfaces, RefitReport, bone_surfaces, ring_cap, tangent_ring_cap
from bonecad.settings import NurbsSettings
from bonecad.splines.surface import BSplineSurface

APEX_FILLS: tuple[str, ...] = ("ring", "patch")
#: face names, from the distal apex up
FACE_NAMES = ("distal_apex_cap", "distal", "shaft", "proximal", "proximal_apex_cap")


@dataclass(frozen=True)
class NurbsModel(ShapePickling):
    """The sewn NURBS baseline in scanner coordinates (mm).

    surfaces : one numpy surface per face, named by region (``surface.region``); u
        runs round the bone, v from the distal towards the proximal apex, and
        S_u x S_v points outwards (or inwards where ``surface.reversed``: the
        fill-hole patch, whose parametrisation OpenCascade chooses)
    shape : the OCP TopoDS_Solid
    face_names : (region name, TopoDS_Face) of every face of ``shape``
    volume_mm3 : the solid's volume (its area is the analysis' CAD -> mesh area)
    refits : deviation of the compatible (common-knot) curves per region
    boundary_gap_mm : largest distance between the shaft's end iso-curves and the
        end surfaces' boundary iso-curves (distal, proximal); 0 by construction
    boundary_shift_mm : how far those iso-curves lie from the shaft's own first and
        last contour sections, which they replace
    patch_errors : for apex_fill "patch", per cap the G0 (mm) and G1 (rad) errors
        OpenCascade reports for the plate surface
    """

    surfaces: tuple[BSplineSurface, ...]
    shape: object
    face_names: tuple[tuple[str, object], ...]
    apex_fill: str
    joins: str
    volume_mm3: float
    refits: tuple[RefitReport, ...]
    boundary_gap_mm: tuple[float, float]
    boundary_shift_mm: tuple[float, float]
    patch_errors: dict = field(default_factory=dict)
    timings_s: dict = field(default_factory=dict)

    @property
    def faces(self) -> int:
        return len(self.face_names)

    @property
    def control_points(self) -> int:
        """Total poles of all faces (a cone's collapsed apex row counts once per pole, as in the file)."""
        return sum(s.control_points for s in self.surfaces)

    @property
    def solid(self):
        """The model as a build123d Solid."""
        return to_build123d(self.shape)

    def surface(self, region: str) -> BSplineSurface:
        for s in self.surfaces:
            if s.region == region:
                return s
        raise KeyError(f"no face named {region!r}; faces are {[s.region for s in self.surfaces]}")

    def summary(self) -> dict:
        """Figures for report.json: faces, control points, volume, refit accuracy, seams, timings."""
        return {
            "faces": self.faces,
            "control_points": self.control_points,
            "apex_fill": self.apex_fill,
            "joins": self.joins,
            "volume_mm3": round(self.volume_mm3, 3),
            "surfaces": [s.to_dict() | {"control_points": s.control_points} for s in self.surfaces],
            "compatible_curves": [r.to_dict() for r in self.refits],
            "boundary_gap_mm": [float(g) for g in self.boundary_gap_mm],
            "boundary_shift_mm": [round(float(g), 5) for g in self.boundary_shift_mm],
            "patch_errors": self.patch_errors,
            "timings_s": {k: round(v, 3) for k, v in self.timings_s.items()},
        }


def _boundary_gap(a: BSplineSurface, va: float, b: BSplineSurface, vb: float, samples: int = 560) -> float:
    u = np.linspace(0.0, 1.0, samples, endpoint=False)
    gap = a.evaluate(u, np.full_like(u, va)).points - b.evaluate(u, np.full_like(u, vb)).points
    return float(np.linalg.norm(gap, axis=1).max())


def build_nurbs(contours: ContourSet, *, settings: NurbsSettings) -> NurbsModel:
    """Loft, connect, cap and sew the contour curves into a closed NURBS solid (scanner mm).

    Parameters
    ----------
    contours : the three regions' curves (bone coordinates) with their frame
    settings : ``apex_fill`` "ring" (ruled cone from the apex to the ring of curve
        ends, the paper's ring of 28 lines; with G1 joins a cubic cap tangent to the
        end surface) or "patch" (fill-hole plate surface, G1 to the end surface);
        ``joins`` "G1" (the shaft tangent to the ends, the caps to the ends: the
        model offsets in OpenCascade) or "C0" (the paper's); the sewing tolerance (mm)

    Raises
    ------
    ValueError for an unknown ``apex_fill``; FitError when a region cannot be
    skinned; KernelError when OpenCascade fails or the result is not one valid
    closed solid of positive volume.
    """
    apex_fill = settings.apex_fill
    if apex_fill not in APEX_FILLS:
        raise ValueError(f"apex_fill must be one of {APEX_FILLS}, got {apex_fill!r}")
    tolerance = settings.sewing_tolerance_mm
    timings: dict[str, float] = {}

    start = time.perf_counter()
    bone = bone_surfaces(contours, settings.joins)
    gaps = (_boundary_gap(bone.distal, 1.0, bone.shaft, 0.0), _boundary_gap(bone.shaft, 1.0, bone.proximal, 0.0))
    timings["surfaces"] = time.perf_counter() - start

    start = time.perf_counter()
    frame = contours.frame
    surfaces = _caps_and_sides(bone, apex_fill, settings.joins)
    scanner = [s.transformed(frame.axes, frame.origin) for s in surfaces]
    named = [(s.region, occ.make_face(s)) for s in scanner]
    patch_errors = {}
    if apex_fill == "patch":
        by_name = dict(named)
        for cap, side, ring in (("distal_apex_cap", "distal", bone.distal_ring),
                                ("proximal_apex_cap", "proximal", bone.proximal_ring)):
            edge = occ.ring_edge(by_name[side], ring.transformed(frame.axes, frame.origin))
            face, g0, g1 = occ.fill_patch(edge, by_name[side], tolerance_mm=tolerance)
            patch_errors[cap] = {"g0_mm": g0, "g1_rad": g1}
            named.append((cap, face))
    named.sort(key=lambda item: FACE_NAMES.index(item[0]))
    timings["faces"] = time.perf_counter() - start

    start = time.perf_counter()
    solid, face_names = brep.named_solid(named, tolerance_mm=tolerance)
    reversed_ = {name: brep.face_is_reversed(f) for name, f in face_names}
    final = []
    for s in scanner:
        if reversed_[s.region]:
            raise KernelError(f"the {s.region} face came out inward; the loft orientation is wrong")
        final.append(s)
    for name in ("distal_apex_cap", "proximal_apex_cap"):
        if apex_fill == "patch":
            final.append(occ.from_face(dict(face_names)[name], name, reversed_=reversed_[name]))
    final.sort(key=lambda s: FACE_NAMES.index(s.region))
    timings["sew"] = time.perf_counter() - start

    start = time.perf_counter()
    if not brep.is_valid(solid):
        raise KernelError("the sewn NURBS solid is not valid (BRepCheck_Analyzer)")
    free = brep.free_edge_count(solid)
    if free:
        raise KernelError(f"the sewn NURBS solid has {free} free edges")
    volume = brep.volume_mm3(solid)
    if not volume > 0:
        raise KernelError(f"the NURBS solid has volume {volume:.1f} mm^3: it is inside out")
    timings["check"] = time.perf_counter() - start
    return NurbsModel(
        surfaces=tuple(final),
        shape=solid,
        face_names=tuple(sorted(face_names, key=lambda item: FACE_NAMES.index(item[0]))),
        apex_fill=apex_fill,
        joins=settings.joins,
        volume_mm3=volume,
        refits=bone.refits,
        boundary_gap_mm=gaps,
        boundary_shift_mm=bone.boundary_shift_mm,
        patch_errors=patch_errors,
        timings_s=timings,
    )


def _caps_and_sides(bone: BoneSurfaces, apex_fill: str, joins: str) -> list[BSplineSurface]:
    """The side faces, plus the ring caps when ``apex_fill`` is "ring" (bone coordinates): cones for C0
    joins, caps tangent to the ends for G1."""
    sides = [bone.distal, bone.shaft, bone.proximal]
    if apex_fill != "ring":
        return sides
    if joins == "G1":
        return [
            tangent_ring_cap(bone.distal_ring, bone.distal_outward, bone.distal_apex, np.array([0.0, 0.0, 1.0]),
                             "distal_apex_cap", apex_first=True),
            *sides,
            tangent_ring_cap(bone.proximal_ring, bone.proximal_outward, bone.proximal_apex, bone.proximal_axis,
                             "proximal_apex_cap", apex_first=False),
        ]
    return [
        ring_cap(bone.distal_ring, bone.distal_apex, "distal_apex_cap", apex_first=True),
        *sides,
        ring_cap(bone.proximal_ring, bone.proximal_apex, "proximal_apex_cap", apex_first=False),
    ]
