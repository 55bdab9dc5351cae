"""The bone of a run: its profile (``--bone``, or recognised) and the frame strategy the profile names."""
from __future__ import annotations

from dataclasses import replace
from typing import Literal

from bonecad.anatomy.femur import femur_frame
from bonecad.anatomy.frame import AnatomicalFrame, anatomical_frame
from bonecad.anatomy.recognise import recognise_bone
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.settings import BoneProfile, Settings, load_profile


def kept_body(settings: Settings) -> Literal["tibia", "femur"]:
    """The body the intake keeps from a leg: the named bone's profile's; the tibia's for "auto" (a leg is
    modelled by its tibia unless --bone femur is given; the dropped femur is named with that hint)."""
    name = settings.pipeline.bone
    return load_profile("tibia" if name == "auto" else name).body


def bone_profile(bone: BoneMesh, settings: Settings) -> BoneProfile:
    """The profile of the recognised bone (``settings.pipeline.bone`` "auto"), or of the bone named there
    once the mesh is not clearly the other bone (InputError, exit 2, naming what it looks like)."""
    return load_profile(recognise_bone(bone, femur=settings.femur, plausible=settings.units,
                                       asked=settings.pipeline.bone))


def bone_settings(bone: BoneMesh, settings: Settings) -> Settings:
    """The run's settings for this bone: its profile's own values laid over them, the bone named (and
    checked: see ``bone_profile``); for a mesh segmented from a CT, the T-spline's target at least
    ``[tspline] segmented_share_within_mm`` (the larger share, the smaller distance)."""
    profile = bone_profile(bone, settings)
    tuned = settings.for_bone(profile)
    if bone.segmented:
        (share, mm), (ct_share, ct_mm) = tuned.tspline.target_share_within_mm, tuned.tspline.segmented_share_within_mm
        tuned = tuned.replace("tspline", target_share_within_mm=[max(share, ct_share), min(mm, ct_mm)])
    return replace(tuned, pipeline=replace(tuned.pipeline, bone=profile.frame))


def named_bone(bone: BoneMesh, settings: Settings) -> BoneMesh:
    """The bone with its kept body (the intake's first) named as the bone of ``settings`` (``bone_settings``
    named it): a femur alone in its file, read with --bone auto, was kept by the tibia's rule."""
    name = settings.pipeline.bone
    if not bone.bodies or bone.bodies[0].role == name:
        return bone
    return replace(bone, bodies=(replace(bone.bodies[0], role=name), *bone.bodies[1:]))


def bone_frame(bone: BoneMesh, settings: Settings) -> AnatomicalFrame:
    """The anatomical frame by the profile's strategy: ``settings.pipeline.bone`` as ``bone_settings`` named
    it ("auto" recognises it here)."""
    name = settings.pipeline.bone
    profile = bone_profile(bone, settings) if name == "auto" else load_profile(name)
    if profile.frame == "femur":
        return femur_frame(bone, settings=settings.femur)
    return anatomical_frame(bone, settings=settings.anatomy, plausible=settings.units)
