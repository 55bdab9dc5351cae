"""Runs the stages in order, times them and writes their outputs.

input (CT volume | mesh) -> BoneMesh -> AnatomicalFrame -> ContourSet
    -> NurbsModel, TSplineModel -> Analysis -> exports + report

Every command of the CLI is one function here, writing through
``staged_output`` so a failure leaves no partial files in the output folder.
"""
from __future__ import annotations

import importlib
import json
import logging
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterator

import numpy as np

from bonecad.anatomy.frame import AnatomicalFrame, anatomical_frame
from bonecad.run import executor as parallel
from bonecad.config import load_config
from bonecad.contours.curves import ContourSet, bone_coordinates, contour_curves
from bonecad.occ.exchange import frame_entities, write_iges, write_step
from bonecad.staging import staged_output
from bonecad.errors import InputError
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.mesh.intake import Units, load_bone

log = logging.getLogger("bonecad")


class Timings(dict):
    """Stage name -> seconds, filled by the ``stage`` context manager.

    Stages run on the second core (``bonecad.run.executor``) overlap the others, so
    the stage times do not add up to the run's time: ``wall_s`` is that, from
    the creation of the object.
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.started = time.perf_counter()

    def wall_s(self) -> float:
        return round(time.perf_counter() - self.started, 3)

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


def segment_ct(path: str | Path) -> BoneMesh:
    """The tibia's surface from a CT volume (DICOM folder, NIfTI, NRRD, MHA), world mm (LPS)."""
    from bonecad.imaging import segment_bone
    from bonecad.imaging.volume import read_volume

    log.info("reading CT volume %s", path)
    volume = read_volume(path)
    log.info("segmenting bone (%d x %d x %d voxels)", *volume.hu.shape[::-1])
    return segment_bone(volume)


def load_input(path: str | Path, *, units: Units = "auto", config: dict | None = None) -> BoneMesh:
    """The tibia mesh of an input: read a mesh file, or segment a CT volume."""
    return segment_ct(path) if is_volume(path) else load_bone(path, units=units, config=config)


def run_segment(path: str | Path, out_mesh: str | Path) -> BoneMesh:
    """``bonecad segment``: the tibia's surface from a CT volume, written as a mesh file (STL, PLY, OBJ, OFF)."""
    from bonecad.staging import staged_file

    out_mesh = Path(out_mesh)
    if out_mesh.suffix.lower() not in (".stl", ".ply", ".obj", ".off"):
        raise InputError(f"unsupported mesh format '{out_mesh.suffix}' (use .stl, .ply, .obj or .off)", out_mesh)
    bone = segment_ct(path)
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
    """(name, edge) of every contour curve, mapped back to scanner coordinates (exact: affine map of poles)."""
    from bonecad.occ.curves import to_edge

    frame = contours.frame
    return [(c.name, to_edge(c.curve.transformed(frame.axes, frame.origin), c.name)) for c in contours.all_curves()]


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


def write_curves(contours: ContourSet, bone: BoneMesh, out_dir: Path) -> None:
    """curves.step and curves.iges (the contour curves and the reference entities, scanner mm) and curves.png."""
    from bonecad.render.curves import curves_png

    frame = contours.frame
    tree = ("bonecad_curves", [("contour_curves", curve_shapes(contours)),
                               ("reference_entities", frame_entities(frame))])
    write_step(tree, out_dir / "curves.step")
    write_iges(tree, out_dir / "curves.iges")
    vertices, faces = bone_coordinates(bone, frame)
    curves_png(out_dir / "curves.png", vertices, faces, contours)


STAGES = ("frame", "curves", "models")
MODELS = ("nurbs", "tspline")


@dataclass
class Reconstruction:
    """Everything one run produced: the stages' results, the per-model analysis, timings and files.

    ``models`` maps "nurbs"/"tspline" to the model objects; ``reports`` to their
    analysis (deviation, continuity, figures); ``files`` names the outputs in ``out_dir``.
    """

    bone: BoneMesh
    frame: AnatomicalFrame
    contours: ContourSet | None = None
    models: dict = field(default_factory=dict)
    reports: dict = field(default_factory=dict)
    timings_s: dict = field(default_factory=dict)
    out_dir: Path | None = None
    files: list[str] = field(default_factory=list)
    wall_s: float | None = None  # the whole run (stage times on the second core overlap)

    def figure(self, name: str) -> Path:
        """Path of an output figure, e.g. ``figure("nurbs_zebra.png")``."""
        if self.out_dir is None or name not in self.files:
            raise InputError(f"no figure {name!r}; this run wrote {self.files}")
        return self.out_dir / name


def reconstruct_bone(
    bone: BoneMesh,
    out_dir: str | Path,
    *,
    until: str = "models",
    models: tuple[str, ...] = MODELS,
    apex_fill: str | None = None,
    compare_tensor_product: bool | None = None,
    config: dict | None = None,
    distal_boundary_mm: float | None = None,
    proximal_boundary_mm: float | None = None,
    timings: Timings | None = None,
) -> Reconstruction:
    """Run the stages from the frame up to ``until`` and write their files into ``out_dir``.

    frame: frame.json and curves.step (the reference entities);
    curves: also the contour curves in curves.step, curves.iges, curves.json and curves.png;
    models: also each model's STEP/IGES (nurbs.*, tspline.*), its analysis figures,
    report.json and report.html.
    """
    if until not in STAGES:
        raise ValueError(f"until must be one of {STAGES}, got {until!r}")
    unknown = set(models) - set(MODELS)
    if unknown or not models:
        raise InputError(f"models must be among {MODELS}, got {list(models)}")
    config = config or load_config()
    background = bool(config["pipeline"]["background_jobs"])
    timings = timings if timings is not None else Timings()
    out_dir = Path(out_dir)
    with staged_output(out_dir) as stage_dir, parallel.jobs(background) as jobs:
        boundaries = {"distal_boundary_mm": distal_boundary_mm, "proximal_boundary_mm": proximal_boundary_mm}
        if until == "frame":
            with timings.stage("anatomical frame"):
                frame = anatomical_frame(bone, config=config, **boundaries)
            with timings.stage("reference entities to STEP"):
                write_step(("reference_entities", frame_entities(frame)), stage_dir / "curves.step")
            result = Reconstruction(bone=bone, frame=frame, timings_s=timings, out_dir=out_dir)
        else:
            # the frame and the curves on the second core while this process imports, once, what the
            # models need (the children forked later inherit it instead of importing it again)
            front = jobs.start(_frame_and_curves, bone, config, jobs, **boundaries)
            with timings.stage("OpenCascade and matplotlib imports"):
                importlib.import_module("bonecad.occ.brep")
                importlib.import_module("bonecad.render.figures")
            frame, contours, front_timings = front.result()[0]
            timings.update(front_timings)
            result = Reconstruction(bone=bone, frame=frame, contours=contours, timings_s=timings, out_dir=out_dir)
            # the second core: curves.step/.iges/.png, then the NURBS model, its files and analysis
            side = jobs.start(_curve_files_and_nurbs, result.contours, bone, stage_dir,
                              nurbs=until == "models" and "nurbs" in models, apex_fill=apex_fill, config=config)
            write_json(contours_dict(result.contours), stage_dir / "curves.json")
            for name, summary in result.contours.summary().items():
                log.info("%s: %d curves, worst deviation %.3f mm (tolerance %s mm, %d within)", name,
                         summary["curves"], summary["worst_max_deviation_mm"], summary["tolerance_mm"],
                         summary["within_tolerance"])
            if until == "models":
                _build_models(result, stage_dir, models, compare_tensor_product, config, timings, jobs, side)
            else:
                timings.update(side.result()[0]["timings"])
        # no timings (report.json and the log have them): the same input gives the same frame.json
        write_json({"input": mesh_summary(bone), **frame.as_dict()}, stage_dir / "frame.json")
        result.files = sorted(p.name for p in stage_dir.iterdir())
    result.timings_s = dict(timings)
    result.wall_s = timings.wall_s()
    return result


def _frame_and_curves(bone: BoneMesh, config: dict, jobs: parallel.JobGroup, *, distal_boundary_mm: float | None,
                      proximal_boundary_mm: float | None) -> tuple[AnatomicalFrame, ContourSet, dict]:
    """The anatomical frame and the contour curves, with their stage times (picklable: a background job)."""
    timings = Timings()
    with timings.stage("anatomical frame"):
        frame = anatomical_frame(bone, config=config, distal_boundary_mm=distal_boundary_mm,
                                 proximal_boundary_mm=proximal_boundary_mm)
    with timings.stage("contour curves"):
        contours = contour_curves(bone, frame, config=config, jobs=jobs)
    return frame, contours, dict(timings)


def _curve_files_and_nurbs(contours: ContourSet, bone: BoneMesh, stage_dir: Path, *, nurbs: bool, apex_fill,
                           config: dict) -> dict:
    """curves.step, curves.iges, curves.png, then (``nurbs``) the NURBS model, its files and its analysis.

    Returns {"timings": {stage: s}, "model": NurbsModel, "report": ModelReport} (picklable: it runs as
    a background job).
    """
    timings = Timings()
    with timings.stage("curves to STEP, IGES and PNG"):
        write_curves(contours, bone, stage_dir)
    out: dict = {"timings": timings}
    if nurbs:
        from bonecad.analysis.model import analyse_model
        from bonecad.nurbs_model.model import build_nurbs, write_nurbs

        with timings.stage("NURBS model"):
            model = build_nurbs(contours, apex_fill=apex_fill, config=config)
            write_nurbs(model, stage_dir)
        with timings.stage("NURBS analysis"):
            out["report"] = analyse_model("nurbs", model.shape, bone, contours.frame, stage_dir,
                                          info=model.summary(), face_names=list(model.face_names))
        out["model"] = model
    return out


def _build_models(
    result: Reconstruction, stage_dir: Path, models, compare_tensor_product, config, timings: Timings,
    jobs: parallel.JobGroup, side: parallel.Job,
) -> None:
    """The T-spline model, its exports and analysis, beside the ``side`` job (curve files and the
    NURBS model, on the second core: ``bonecad.run.executor``), then report.json/report.html.

    The T-spline model's zebra figure and continuity are made on the second core
    while its deviation is measured. Stage times of the side job are its own.
    """
    from bonecad.analysis.model import analyse_model
    from bonecad.export.report import write_report

    bone, frame, contours = result.bone, result.frame, result.contours
    if "tspline" in models:
        from bonecad.tspline_model.model import build_tspline_model, write_tspline

        with timings.stage("T-spline model"):
            tspline = build_tspline_model(bone, frame, contours, config=config,
                                          compare_tensor_product=compare_tensor_product, jobs=jobs)
            write_tspline(tspline, stage_dir)
        result.models["tspline"] = tspline
        with timings.stage("T-spline analysis"):
            result.reports["tspline"] = analyse_model(
                "tspline", tspline.shape, bone, frame, stage_dir,
                info={"faces": len(tspline.face_names), **tspline.summary()},
                face_names=list(tspline.face_names), jobs=jobs,
            )
    with timings.stage("waiting for the second core"):
        done = side.result()[0]
    timings.update(done["timings"])
    if "nurbs" in models:
        result.models["nurbs"], result.reports["nurbs"] = done["model"], done["report"]
    with timings.stage("report"):
        write_report(
            stage_dir,
            input_summary={**mesh_summary(bone), "side": frame.side},
            frame=frame.as_dict(),
            models=[result.reports[m] for m in MODELS if m in result.reports],
            timings_s={**timings, "total (wall)": timings.wall_s()},
        )


def reconstruct(
    source: str | Path,
    out_dir: str | Path | None = None,
    *,
    until: str = "models",
    models: tuple[str, ...] = MODELS,
    apex_fill: str | None = None,
    compare_tensor_product: bool | None = None,
    units: Units = "auto",
    config: dict | None = None,
    distal_boundary_mm: float | None = None,
    proximal_boundary_mm: float | None = None,
) -> Reconstruction:
    """The whole pipeline on a mesh file or CT volume; outputs in ``out_dir`` (a new temporary folder if None)."""
    config = config or load_config()
    timings = Timings()
    if out_dir is None:
        out_dir = Path(tempfile.mkdtemp(prefix="bonecad-"))
    with timings.stage("input"):
        bone = load_input(source, units=units, config=config)
    return reconstruct_bone(
        bone, out_dir, until=until, models=models, apex_fill=apex_fill,
        compare_tensor_product=compare_tensor_product, config=config,
        distal_boundary_mm=distal_boundary_mm, proximal_boundary_mm=proximal_boundary_mm, timings=timings,
    )


def run_demo(out_dir: str | Path, *, config: dict | None = None) -> Reconstruction:
    """``bonecad demo``: the embedded phantom as a real case starts, from its CT, through every stage.

    Writes the phantom's mesh (phantom.stl) and its synthetic CT (0.8 mm voxels,
    30 HU noise) as NIfTI (phantom_ct.nii.gz) and as a DICOM series (phantom_ct/),
    then runs the pipeline on the DICOM series.
    """
    from bonecad.imaging import mesh_to_ct
    from bonecad.imaging.phantom_tibia import phantom_tibia
    from bonecad.imaging.volume import write_dicom_series, write_nifti

    config = config or load_config()
    timings = Timings()
    with staged_output(out_dir) as stage_dir:
        with timings.stage("phantom tibia and its CT"):
            phantom = phantom_tibia()
            phantom.to_trimesh().export(stage_dir / "phantom.stl")
            ct = mesh_to_ct(phantom.vertices, phantom.faces, voxel_mm=0.8)
            write_nifti(ct, stage_dir / "phantom_ct.nii.gz")
            dicom = write_dicom_series(ct, stage_dir / "phantom_ct")
        with timings.stage("segmentation of the phantom CT"):
            # named by where the series will be, not by the staging folder
            bone = replace(load_input(dicom, config=config), source=str(Path(out_dir) / dicom.name))
        result = reconstruct_bone(bone, stage_dir, config=config, timings=timings)
    result.out_dir = Path(out_dir)
    return result
