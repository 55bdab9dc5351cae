"""Which bone a mesh is (``--bone auto``): a femur has a head (a sphere) at its narrow end, a tibia none."""
from __future__ import annotations

from bonecad.anatomy.femur import head_at_narrow_end
from bonecad.errors import InputError
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.settings import FemurSettings, UnitsSettings


def recognise_bone(bone: BoneMesh, *, femur: FemurSettings, plausible: UnitsSettings) -> str:
    """"femur" or "tibia"; InputError naming what the mesh looks like when it is neither."""
    head, _, length = head_at_narrow_end(bone, femur)
    lo_f, hi_f = femur.length_mm
    lo_t, hi_t = plausible.tibia_length_mm
    if head is not None and lo_f <= length <= hi_f:
        return "femur"
    if head is None and lo_t <= length <= hi_t:
        return "tibia"
    looks = (f"a {length:.0f} mm bone with a {head.radius_mm:.0f} mm sphere (a head) at its narrow end"
             if head is not None else f"a {length:.0f} mm bone with no head (sphere) at its narrow end")
    raise InputError(f"neither a tibia ({lo_t:.0f}-{hi_t:.0f} mm, no head) nor a femur ({lo_f:.0f}-{hi_f:.0f} mm, a "
                     f"head at the narrow end): {looks}; pass --bone to say which it is", bone.source or None)
