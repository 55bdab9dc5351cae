"""The bone of a run: its profile (``--bone``, or recognised) and the frame strategy the profile names."""
from __future__ import annotations

from dataclasses import replace

from bonecad.anatomy.femur import femur_frame
from bonecad.anatomy.frame import AnatomicalFrame, anatomical_frame
from bonecad.anatomy.recognise import recognise_bone
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.settings import BoneProfile, Settings, load_profile


def bone_profile(bone: BoneMesh, settings: Settings) -> BoneProfile:
    """The profile of ``settings.pipeline.bone``, or of the recognised bone when it is "auto"."""
    if settings.pipeline.bone == "auto":
        return load_profile(recognise_bone(bone, femur=settings.femur, plausible=settings.units))
    return load_profile(settings.pipeline.bone)


def bone_settings(bone: BoneMesh, settings: Settings) -> Settings:
    """The run's settings for this bone: its profile's own values laid over them, the bone named."""
    profile = bone_profile(bone, settings)
    tuned = settings.for_bone(profile)
    return replace(tuned, pipeline=replace(tuned.pipeline, bone=profile.frame))


def bone_frame(bone: BoneMesh, settings: Settings) -> AnatomicalFrame:
    """The anatomical frame by the profile's strategy (``settings.pipeline.bone``: "auto" recognises it)."""
    if bone_profile(bone, settings).frame == "femur":
        return femur_frame(bone, settings=settings.femur)
    return anatomical_frame(bone, settings=settings.anatomy, plausible=settings.units)
