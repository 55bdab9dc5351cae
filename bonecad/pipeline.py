"""Runs the stages in order, times them and writes their outputs.

input (CT volume | mesh) -> BoneMesh -> AnatomicalFrame -> ContourSet
    -> NurbsModel, TSplineModel -> Analysis -> exports + report

Every command of the CLI is one function here, writing through
``staged_output`` so a failure leaves no partial files in the output folder.
"""
from __future__ import annotations

import json
import logging
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np

from .anatomy.frame import AnatomicalFrame, anatomical_frame
from .config import load_config
from .curves.contours import ContourSet, bone_coordinates, contour_curves
from .io.cad import compound, frame_shapes, write_iges, write_step
from .io.output import staged_output
from .mesh.bone_mesh import BoneMesh
from .errors import InputError
from .mesh.intake import Units, load_bone

log = logging.getLogger("bonecad")


class Timings(dict):
    """Stage name -> seconds, filled by the ``stage`` context manager."""

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        log.info("%s ...", name)
        start = time.perf_counter()
        yield
        self[name] = round(time.perf_counter() - start, 3)
        log.info("%s done in %.2f s", name, self[name])


def write_json(data: dict, path: Path) -> None:
    path.write_text(json.dumps(data, indent=2, sort_keys=False) + "\n")


def mesh_summary(bone: BoneMesh) -> dict:
    """Input summary for reports: file, units, bodies, repairs."""
    return {
        "file": bone.source,
        "units": bone.units,
        "triangles": bone.triangle_count,
        "watertight": bone.watertight,
        "bodies": [
            {
                "role": b.role,
                "triangles": b.triangles,
                "volume_mm3": round(b.volume_mm3, 1),
                "length_mm": round(b.length_mm, 1),
                "centroid": np.round(b.centroid, 3).tolist(),
            }
            for b in bone.bodies
        ],
        "repairs": list(bone.repairs),
    }


VOLUME_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd", ".dcm", ".ima")


def is_volume(path: str | Path) -> bool:
    """True for a CT volume (a DICOM folder or a volume file), False for a mesh file."""
    path = Path(path)
    return path.is_dir() or path.name.lower().endswith(VOLUME_SUFFIXES)


def load_input(path: str | Path, *, units: Units = "auto", config: dict | None = None) -> BoneMesh:
    """The tibia mesh of an input: read a mesh file, or segment a CT volume (DICOM folder, NIfTI, NRRD, MHA)."""
    if is_volume(path):
        from .imaging import segment_bone
        from .io.volume import read_volume

        log.info("reading CT volume %s", path)
        volume = read_volume(path)
        log.info("segmenting bone (%d x %d x %d voxels)", *volume.hu.shape[::-1])
        return segment_bone(volume)
    return load_bone(path, units=units, config=config)


def run_segment(path: str | Path, out_mesh: str | Path) -> BoneMesh:
    """``bonecad segment``: the tibia's surface from a CT volume, written as a mesh file (STL, PLY, OBJ, OFF)."""
    from .imaging import segment_bone
    from .io.output import staged_file
    from .io.volume import read_volume

    out_mesh = Path(out_mesh)
    if out_mesh.suffix.lower() not in (".stl", ".ply", ".obj", ".off"):
        raise InputError(f"unsupported mesh format '{out_mesh.suffix}' (use .stl, .ply, .obj or .off)", out_mesh)
    bone = segment_bone(read_volume(path))
    with staged_file(out_mesh) as tmp:
        bone.to_trimesh().export(tmp, file_type=out_mesh.suffix[1:].lower())
    return bone


def inspect(path: str | Path, *, units: Units = "auto", config: dict | None = None) -> dict:
    """What ``bonecad inspect`` prints: the input summary, the tibia's side and frame figures."""
    config = config or load_config()
    bone = load_bone(path, units=units, config=config)
    frame = anatomical_frame(bone, config=config)
    summary = mesh_summary(bone)
    summary["side"] = frame.side
    summary["mechanical_axis_length_mm"] = round(frame.mechanical_length_mm, 2)
    summary["plateau_semi_axes_mm"] = np.round(frame.plateau.semi_axes_mm, 2).tolist()
    return summary


def curve_shapes(contours: ContourSet) -> list:
    """Named edges of every contour curve, mapped back to scanner coordinates (exact: affine map of poles)."""
    from .curves.occ import to_edge

    frame = contours.frame
    return [to_edge(c.curve.transformed(frame.axes, frame.origin), c.name) for c in contours.all_curves()]


def contours_dict(contours: ContourSet) -> dict:
    """curves.json: per curve its poles and knots (scanner mm), achieved deviation, tolerance, repairs."""
    frame = contours.frame
    curves = []
    for c in contours.all_curves():
        scanner = c.curve.transformed(frame.axes, frame.origin)
        curves.append({
            "name": c.name,
            "region": c.region,
            "index": c.index,
            "angle_deg": c.angle_deg,
            "level_mm": None if c.level_mm is None else round(c.level_mm, 4),
            "degree": c.curve.degree,
            "periodic": c.curve.periodic,
            "control_points": np.round(scanner.control_points, 6).tolist(),
            "knots": np.round(scanner.knots, 12).tolist(),
            "tolerance_mm": c.tolerance_mm,
            "max_deviation_mm": round(c.max_deviation_mm, 5),
            "rms_deviation_mm": round(c.rms_deviation_mm, 5),
            "within_tolerance": c.within_tolerance,
            "exceeds_tolerance_by_mm": round(max(0.0, c.max_deviation_mm - c.tolerance_mm), 5),
            "repairs": list(c.repairs),
        })
    return {
        "coordinates": "input (scanner) coordinates, mm",
        "regions": contours.summary(),
        "shaft_loft_error_p99_mm": round(contours.shaft_fit_error_mm, 4),
        "notes": list(contours.notes),
        "curves": curves,
    }


def run_stages(
    bone: BoneMesh,
    out_dir: str | Path,
    *,
    until: str = "curves",
    config: dict | None = None,
    distal_boundary_mm: float | None = None,
    proximal_boundary_mm: float | None = None,
) -> tuple[AnatomicalFrame, ContourSet | None]:
    """Run the stages up to ``until`` ("frame" or "curves") and write their files into ``out_dir``.

    frame: frame.json and curves.step (the reference entities);
    curves: also the contour curves in curves.step, curves.iges, curves.json and curves.png.
    """
    from .curves.plot import curves_png

    if until not in ("frame", "curves"):
        raise ValueError(f"until must be 'frame' or 'curves', got {until!r}")
    config = config or load_config()
    timings = Timings()
    contours = None
    with staged_output(out_dir) as stage_dir:
        with timings.stage("anatomical frame"):
            frame = anatomical_frame(
                bone, config=config, distal_boundary_mm=distal_boundary_mm, proximal_boundary_mm=proximal_boundary_mm
            )
        entities = compound(frame_shapes(frame), "reference_entities")
        if until == "frame":
            with timings.stage("reference entities to STEP"):
                write_step(entities, stage_dir / "curves.step")
        else:
            with timings.stage("contour curves"):
                contours = contour_curves(bone, frame, config=config)
            with timings.stage("curves to STEP and IGES"):
                shapes = compound([compound(curve_shapes(contours), "contour_curves"), entities], "bonecad_curves")
                write_step(shapes, stage_dir / "curves.step")
                write_iges(shapes, stage_dir / "curves.iges")
            with timings.stage("curves figure"):
                vertices, faces = bone_coordinates(bone, frame)
                curves_png(stage_dir / "curves.png", vertices, faces, contours)
            write_json({**contours_dict(contours), "timings_s": dict(timings)}, stage_dir / "curves.json")
            for name, summary in contours.summary().items():
                log.info("%s: %d curves, worst deviation %.3f mm (tolerance %s mm, %d within)", name,
                         summary["curves"], summary["worst_max_deviation_mm"], summary["tolerance_mm"],
                         summary["within_tolerance"])
        write_json({"input": mesh_summary(bone), **frame.as_dict(), "timings_s": dict(timings)}, stage_dir / "frame.json")
    return frame, contours


def run_demo(out_dir: str | Path, *, config: dict | None = None) -> None:
    """``bonecad demo``: the embedded phantom as a real case starts, from its CT, through every stage.

    Writes the phantom's mesh (phantom.stl) and synthetic CT (phantom_ct.nii.gz),
    then runs the pipeline on that CT.
    """
    from .imaging import mesh_to_ct
    from .imaging.phantom_tibia import phantom_tibia
    from .io.volume import write_nifti

    config = config or load_config()
    timings = Timings()
    with staged_output(out_dir) as stage_dir:
        with timings.stage("phantom tibia and its CT"):
            phantom = phantom_tibia()
            phantom.to_trimesh().export(stage_dir / "phantom.stl")
            ct_path = write_nifti(mesh_to_ct(phantom.vertices, phantom.faces, voxel_mm=0.8), stage_dir / "phantom_ct.nii.gz")
        with timings.stage("segmentation of the phantom CT"):
            bone = load_input(ct_path, config=config)
        run_stages(bone, stage_dir, until="curves", config=config)
