"""Which bone a mesh is (``--bone``): a femur has a head (a sphere) at its narrow end, a tibia none."""
from __future__ import annotations

from bonecad.anatomy.femur import head_at_narrow_end
from bonecad.errors import InputError
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.settings import FemurSettings, UnitsSettings


def recognise_bone(bone: BoneMesh, *, femur: FemurSettings, plausible: UnitsSettings, asked: str = "auto") -> str:
    """"femur" or "tibia": the bone ``asked`` ("auto": the one the mesh looks like).

    InputError naming what the mesh looks like when it is neither (for "auto"), or when it is clearly the
    other bone (a bone asked for but matching neither profile is taken as asked: that is what --bone is for)."""
    head, _, length = head_at_narrow_end(bone, femur)
    lo_f, hi_f = plausible.femur_length_mm
    lo_t, hi_t = plausible.tibia_length_mm
    found = ("femur" if head is not None and lo_f <= length <= hi_f
             else "tibia" if head is None and lo_t <= length <= hi_t else None)
    if asked != "auto" and found in (None, asked):
        return asked
    if asked == "auto" and found is not None:
        return found
    looks = (f"a {length:.0f} mm bone with a {head.radius_mm:.0f} mm sphere (a head) at its narrow end"
             if head is not None else f"a {length:.0f} mm bone with no head (sphere) at its narrow end")
    if found is not None:
        raise InputError(f"--bone {asked}, but the mesh looks like a {found}: {looks}; pass --bone {found} "
                         "(or --bone auto)", bone.source or None)
    raise InputError(f"neither a tibia ({lo_t:.0f}-{hi_t:.0f} mm, no head) nor a femur ({lo_f:.0f}-{hi_f:.0f} mm, a "
                     f"head at the narrow end): {looks}; pass --bone to say which it is", bone.source or None)
