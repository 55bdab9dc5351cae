"""Mesh exporters: bone.stl, the tibia's surface bonecad segmented from a CT (world mm, LPS)."""
from __future__ import annotations

from pathlib import Path

from bonecad.export.registry import exporter
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.staging import staged_file


@exporter("bone", "stl")
def bone_stl(bone: BoneMesh, out_dir: Path) -> Path:
    """bone.stl (binary): the polygonal model the paper starts from and the reference of the deviation
    analysis, for a run that segmented it from a CT volume."""
    path = out_dir / "bone.stl"
    with staged_file(path) as tmp:
        bone.to_trimesh().export(tmp, file_type="stl")
    return path
