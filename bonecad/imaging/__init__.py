"""CT volume -> bone mask -> tibia mesh; the synthetic CT phantom; the phantom tibia.

- :func:`segment_bone` CTVolume -> BoneMesh of the tibia (LPS world mm)
- :func:`mesh_to_ct` closed mesh -> synthetic CTVolume (shell, marrow, tissue, blur, noise)
- :func:`round_trip` mesh -> CT -> mesh, with the surface distance to the original
"""
from bonecad.imaging.compare import RoundTrip, SurfaceDistance, round_trip, surface_distance
from bonecad.imaging.phantom import mesh_to_ct
from bonecad.imaging.segment import segment_bone, surface_level

__all__ = ["RoundTrip", "SurfaceDistance", "mesh_to_ct", "round_trip", "segment_bone", "surface_distance",
           "surface_level"]
