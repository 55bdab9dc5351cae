"""The runner: schedules the stages on an executor, renders the figures and exports the files.

input (CT volume | mesh) -> BoneMesh -> AnatomicalFrame -> ContourSet
    -> NurbsModel, TSplineModel -> ModelReport -> exports + report

Stages are pure functions of their inputs and settings; this module alone
decides what runs where. With background jobs (``[pipeline] background_jobs``,
``bonecad.run.executor.Fork``) the second core takes, in turn: the frame and
the contour curves (while this process imports OpenCascade and matplotlib
once, for every later child to inherit), the mesh's local noise and the curve
files and the whole NURBS branch (model, analysis, figures, files) while the
T-spline model is built here, and the T-spline model's zebra figure, continuity and colour
map while its deviation is measured here. The colour maps' pixels of the working copy are
rasterised once, here, before the NURBS branch forks: both models colour the same mesh
(``render.figures.mesh_views``). Every file goes through
``staged_output``: a failure, SIGINT or SIGTERM leaves no partial output.
"""
from __future__ import annotations

import html
import importlib
import logging
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal
from collections.abc import Callable, Iterator, Mapping

import numpy as np

from bonecad.analysis.model import ModelReport, model_continuity, model_deviation, model_fairness, tessellate_model
from bonecad.anatomy.frame import AnatomicalFrame
from bonecad.anatomy.morphometry import measure_tibia
from bonecad.contours.curves import ContourSet, bone_coordinates, contour_curves
from bonecad.errors import InputError
from bonecad.export.registry import export
from bonecad.export.documents import FrameDocument
from bonecad.export.measurements import MeasurementsDocument
from bonecad.export.report import ReportDocument, Tolerances
from bonecad.export.viewer import ViewMesh, input_view, model_view, viewer_html
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.mesh.intake import Units, load_bone
from bonecad.mesh.working import first_pass_target, halves_simplified, with_working_copy
from bonecad.run.bones import bone_frame, bone_settings, kept_body, named_bone
from bonecad.run.executor import (Executor, InProcess, executor_for, freed_memory_reused, helper_thread,
                                   huge_pages)
from bonecad.settings import AnalysisSettings, MeshSettings, Settings, load_profile
from bonecad.splines.tspline.fit import FitStats
from bonecad.staging import staged_file, staged_output

if TYPE_CHECKING:
    from bonecad.render.figures import Coverage
    from bonecad.tspline_model.model import MeshNoise

log = logging.getLogger(__name__)

Until = Literal["frame", "curves", "models"]
#: a progress callback of the T-spline fit: (round, the round's FitStats)
FitProgress = Callable[[int, FitStats], None]
STAGES: tuple[Until, ...] = ("frame", "curves", "models")
MODELS = ("nurbs", "tspline")


class Timings:
    """Stage name -> seconds, kept by the runner (not in the stages' results).

    Stages on the second core overlap the others, so the stage times do not
    add up to the run's wall time (``wall_s``, from the creation of the object).
    """

    def __init__(self) -> None:
        self.started = time.perf_counter()
        self.seconds: dict[str, float] = {}

    def wall_s(self) -> float:
        return round(time.perf_counter() - self.started, 3)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        log.info("%s ...", name)
        start = time.perf_counter()
        yield
        self.seconds[name] = round(time.perf_counter() - start, 3)
        log.info("%s done in %.2f s", name, self.seconds[name])

    def update(self, other: Mapping[str, float]) -> None:
        self.seconds.update(other)


@dataclass(frozen=True)
class Reconstruction:
    """Everything one run produced: the stages' results, the per-model analysis, timings and files.

    ``models`` maps "nurbs"/"tspline" to the model objects; ``reports`` to their
    analysis (deviation, continuity, figures); ``files`` names the outputs in ``out_dir``.
    """

    bone: BoneMesh
    frame: AnatomicalFrame
    contours: ContourSet | None = None
    models: Mapping[str, object] = field(default_factory=dict)
    reports: Mapping[str, ModelReport] = field(default_factory=dict)
    timings_s: Mapping[str, float] = field(default_factory=dict)
    out_dir: Path | None = None
    files: tuple[str, ...] = ()
    wall_s: float | None = None  # the whole run (stage times on the second core overlap)
    views: tuple[ViewMesh, ...] = ()  # the 3-D view's meshes: the input, then each model (decimated)

    def show(self):
        """The report's interactive 3-D view in Jupyter (offline: three.js and the meshes inlined)."""
        from IPython.display import HTML

        page = f"<!DOCTYPE html><html><body>{viewer_html(list(self.views), self.frame.as_dict())}</body></html>"
        return HTML(f"<iframe srcdoc='{html.escape(page, quote=True)}' style='width:100%;height:860px;border:0'>"
                    "</iframe>")

    def figure(self, name: str) -> Path:
        """Path of an output figure, e.g. ``figure("nurbs_zebra.png")``."""
        if self.out_dir is None or name not in self.files:
            raise KeyError(f"no figure {name!r}; this run wrote {list(self.files)}")
        return self.out_dir / name


VOLUME_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd", ".dcm", ".ima")


def is_volume(path: str | Path) -> bool:
    """True for a CT volume (a DICOM folder or a volume file), False for a mesh file."""
    path = Path(path)
    return path.is_dir() or path.name.lower().endswith(VOLUME_SUFFIXES)


def segment_ct(path: str | Path, settings: Settings, *,
               working_copy: Callable[..., BoneMesh] = with_working_copy) -> BoneMesh:
    """The tibia's surface from a CT volume (DICOM folder, NIfTI, NRRD, MHA), world mm (LPS).

    The segmented tibia passes the same fused-bone check as a mesh input: a
    neighbour the segmentation could not separate is an input error naming it."""
    from bonecad.imaging import segment_bone
    from bonecad.imaging.volume import read_volume
    from bonecad.mesh.bodies import check_not_fused
    from bonecad.mesh.intake import longest_bone_mm

    log.info("reading CT volume %s", path)
    volume = read_volume(path)
    log.info("segmenting bone (%d x %d x %d voxels)", *volume.hu.shape[::-1])
    segmented = segment_bone(volume, settings=settings.imaging, mesh_settings=settings.mesh)
    bone = working_copy(segmented, settings.mesh)
    for repair in bone.repairs:
        log.info("%s", repair)
    check_not_fused(bone.work.vertices, bone.work.faces, settings.mesh, longest_bone_mm(settings.units), Path(path))
    return bone


def load_input(path: str | Path, settings: Settings, *, units: Units = "auto",
               working_copy: Callable[..., BoneMesh] = with_working_copy,
               beside: Callable[..., Any] | None = None) -> BoneMesh:
    """The tibia mesh of an input: read a mesh file, or segment a CT volume (either with the working copy of a
    surface denser than the tolerance needs, ``mesh.working``, made by ``working_copy``; a mesh's cleanup
    partly ``beside``, ``load_bone``)."""
    if is_volume(path):
        return segment_ct(path, settings, working_copy=working_copy)
    return load_bone(path, units=units, settings=settings.mesh, plausible=settings.units, keep=kept_body(settings),
                     working_copy=working_copy, beside=beside)


def working_copy_alone(bone: BoneMesh, settings: MeshSettings, area_mm2: float | None,
                       first: tuple[np.ndarray, np.ndarray] | None) -> BoneMesh | None:
    """The working copy ``with_working_copy`` gives ``bone`` (None: none), alone: a background job's result
    (the full mesh stays in the parent)."""
    return with_working_copy(bone, settings, area_mm2=area_mm2, first=first).working


def copy_beside_tree(ex: Executor) -> Callable[..., BoneMesh]:
    """``with_working_copy`` on both cores: the first pass's two halves simplified in a job of ``ex`` and in
    this process, then the rest of the copy in a job while this process builds the full mesh's closest-point
    tree (``BoneMesh.locator``, for the analysis): the costs that grow with the mesh, on both cores."""

    def working_copy(bone: BoneMesh, settings: MeshSettings, *, area_mm2: float | None = None) -> BoneMesh:
        target = first_pass_target(bone.vertices, bone.faces, settings, area_mm2=area_mm2)
        first = None if target is None else halves_simplified(bone.vertices, bone.faces, target, beside=ex.submit)
        job = ex.submit(working_copy_alone, bone, settings, area_mm2, first)
        _ = bone.locator
        return replace(bone, working=job.result())

    return working_copy


def run_segment(path: str | Path, out_mesh: str | Path, settings: Settings) -> BoneMesh:
    """``bonecad segment``: the tibia's surface from a CT volume, written as a mesh file (STL, PLY, OBJ, OFF)."""
    out_mesh = Path(out_mesh)
    if out_mesh.suffix.lower() not in (".stl", ".ply", ".obj", ".off"):
        raise InputError(f"unsupported mesh format '{out_mesh.suffix}' (use .stl, .ply, .obj or .off)", out_mesh)
    bone = segment_ct(path, settings)
    with staged_file(out_mesh) as tmp:
        bone.to_trimesh().export(tmp, file_type=out_mesh.suffix[1:].lower())
    return bone


def inspect(path: str | Path, settings: Settings, *, units: Units = "auto") -> dict:
    """What ``bonecad inspect`` prints: the input summary, the bone's side and frame figures."""
    bone = load_bone(path, units=units, settings=settings.mesh, plausible=settings.units, keep=kept_body(settings))
    settings = bone_settings(bone, settings)
    bone = named_bone(bone, settings)
    frame = bone_frame(bone, settings)
    summary = bone.summary()
    summary["bone"] = frame.bone
    summary["side"] = frame.side
    summary["mechanical_axis_length_mm"] = round(frame.mechanical_length_mm, 2)
    summary["plateau_semi_axes_mm"] = np.round(frame.plateau.semi_axes_mm, 2).tolist()
    return summary


def run_measure(source: str | Path, settings: Settings, *, units: Units = "auto", out: Path | None = None
                ) -> MeasurementsDocument:
    """``bonecad measure``: the tibia's or the femur's morphometric parameters (``bonecad.anatomy.morphometry``,
    ``bonecad.anatomy.femur_morphometry``) from a mesh or a CT volume, written to ``out`` (.json or .csv)
    when given."""
    from bonecad.export.measurements import check_measurements_path, write_measurements

    if out is not None:
        check_measurements_path(out)  # before the work
    bone = load_input(source, settings, units=units)
    settings = bone_settings(bone, settings)
    frame = bone_frame(bone, settings)
    if frame.bone == "femur":
        from bonecad.anatomy.femur_morphometry import measure_femur

        doc = MeasurementsDocument(str(source), measure_femur(bone, frame))
    elif frame.bone == "tibia":
        doc = MeasurementsDocument(str(source), measure_tibia(bone, frame, settings.morphometry))
    else:
        raise InputError(f"bonecad measure measures tibias and femurs; this is a {frame.bone}", source)
    if out is not None:
        write_measurements(doc, out)
    return doc


def reconstruct_bone(
    bone: BoneMesh,
    out_dir: str | Path,
    settings: Settings,
    *,
    until: Until = "models",
    timings: Timings | None = None,
    executor: Executor | None = None,
    progress: FitProgress | None = None,
) -> Reconstruction:
    """Run the stages from the frame up to ``until`` and write their files into ``out_dir``.

    frame: frame.json and curves.step (the reference entities), and bone.stl for a mesh segmented from a CT;
    curves: also the contour curves in curves.step, curves.iges, curves.json and curves.png;
    models: also each model of ``settings.pipeline.models`` (nurbs.*, tspline.*), its
    analysis figures, report.json and report.html.
    executor : where background jobs run (default: forked children when
    ``settings.pipeline.background_jobs`` and fork is possible, else in process).
    progress : called with (round, FitStats) after each round of the T-spline fit (in this process).
    """
    if until not in STAGES:
        raise ValueError(f"until must be one of {STAGES}, got {until!r}")
    models = settings.pipeline.models if until == "models" else ()
    if until == "models" and not models:
        raise InputError("no model to build: [pipeline] models is empty")
    timings = timings if timings is not None else Timings()
    settings = bone_settings(bone, settings)  # the bone's profile: recognised when --bone is auto
    bone = named_bone(bone, settings)
    ex = executor if executor is not None else executor_for(settings.pipeline.background_jobs)
    out_dir = Path(out_dir)
    with staged_output(out_dir) as stage_dir, ex:
        if bone.segmented:
            export("bone", bone, stage_dir)
        if until == "frame":
            with timings.stage("anatomical frame"):
                frame = bone_frame(bone, settings)
            frame_doc = FrameDocument(bone.summary(), frame)
            with timings.stage("reference entities to STEP"):
                export("frame", frame_doc, stage_dir, only=["step"])
            result = Reconstruction(bone=bone, frame=frame)
        else:
            front = ex.submit(frame_and_contours, bone, settings)
            with timings.stage("OpenCascade and matplotlib imports"), ex.shielded():
                for module in ("bonecad.occ.brep", "bonecad.render.figures", "bonecad.export.cad"):
                    importlib.import_module(module)
            if until == "models":
                with timings.stage("closest-point tree of the mesh"):
                    # the tree, its vertex normals, triangle areas and spatial order, built in idle time for
                    # both models' analysis (their jobs fork later); the working copy's for their 3-D views; the
                    # voxel step for the T-spline fit and its noise (a job of its own)
                    _ = bone.locator.vertex_normals, bone.locator.triangle_areas, bone.locator.spatial_order
                    _ = bone.work.locator.vertex_normals
                    _ = bone.voxel_step_mm
            with timings.stage("waiting for the frame and the contour curves"):
                frame, contours, front_timings = front.result()
            timings.update(front_timings)
            frame_doc = FrameDocument(bone.summary(), frame)
            result = _curves_and_models(bone, frame, contours, stage_dir, settings, models, timings, ex, progress)
        # no timings (report.json and the log have them): the same input gives the same frame.json
        export("frame", frame_doc, stage_dir, only=["json"])
        files = tuple(sorted(p.name for p in stage_dir.iterdir()))
    return replace(result, out_dir=out_dir, files=files, timings_s=dict(timings.seconds), wall_s=timings.wall_s())


def frame_and_contours(bone: BoneMesh, settings: Settings
                       ) -> tuple[AnatomicalFrame, ContourSet, dict[str, float]]:
    """The anatomical frame, then the contour curves: the job that runs beside this process's imports.
    Returns them with their stage times (s)."""
    timings = Timings()
    with timings.stage("anatomical frame"):
        frame = bone_frame(bone, settings)
    with timings.stage("contour curves"):
        contours = contour_curves(bone, frame, settings=settings.curves)
    return frame, contours, timings.seconds


def _curves_and_models(bone: BoneMesh, frame: AnatomicalFrame, contours: ContourSet, stage_dir: Path,
                       settings: Settings, models: tuple[str, ...], timings: Timings, ex: Executor,
                       progress: FitProgress | None) -> Reconstruction:
    """The contour curves' files, then the models with their analysis, figures and files, and the report."""
    noise = ex.submit(mesh_noise, bone, frame, settings) if "tspline" in models else None
    for name, summary in contours.summary().items():
        log.info("%s: %d curves, worst deviation %.3f mm (tolerance %s mm, %d within)", name, summary["curves"],
                 summary["worst_max_deviation_mm"], summary["tolerance_mm"], summary["within_tolerance"])
    pixels = None
    if models:
        from bonecad.render.figures import VIEWS, mesh_views

        # the working copy's pixels in the colour maps' views, once for both models (their maps differ in
        # colour only); here, before the NURBS job forks and inherits them, while the noise job runs
        with timings.stage("colour map pixels"):
            pixels = mesh_views(bone.work.vertices, bone.work.faces, frame.axes.T, VIEWS,
                                height_px=settings.analysis.figure_height_px)
    # the second core: curves.step/.iges/.png, then the NURBS model, its analysis, figures and files
    side = ex.submit(curve_files_and_nurbs, contours, bone, stage_dir, settings, "nurbs" in models, pixels)
    export("curves", contours, stage_dir, only=["json"])
    built: dict[str, object] = {}
    reports: dict[str, ModelReport] = {}
    views: dict[str, ViewMesh] = {}
    if "tspline" in models:
        from bonecad.tspline_model.model import build_tspline_model

        with timings.stage("T-spline model"):
            model = build_tspline_model(bone, frame, contours, settings=settings.tspline,
                                        apex_hole_radius_mm=settings.curves.apex_hole_radius_mm,
                                        noise=None if noise is None else noise.result(), progress=progress)
        with timings.stage("T-spline files"):
            export("tspline", model, stage_dir)
        with timings.stage("T-spline analysis"):
            reports["tspline"], views["tspline"] = analyse(
                "tspline", model, bone, frame, stage_dir, settings,
                {"faces": len(model.face_names), **model.summary()}, ex, pixels)
        built["tspline"] = model
    with timings.stage("waiting for the second core"):
        side_timings, nurbs = side.result()
    timings.update(side_timings)
    if nurbs is not None:
        built["nurbs"], reports["nurbs"], views["nurbs"] = nurbs
    views_in_order: tuple[ViewMesh, ...] = ()
    if models:
        from bonecad.render.figures import histograms_png

        shown = [m for m in MODELS if m in reports]
        tolerances = Tolerances.of(settings.tspline)
        # the histograms' figure on the other core, beside the 3-D view, the morphometry and the page
        histograms = ex.submit(histograms_png, stage_dir / "histograms.png",
                               {m: {"whole bone": dev.mesh_to_cad.histogram, **dev.mesh_to_cad.region_histograms}
                                for m in shown if (dev := reports[m].deviation) is not None},
                               tolerance_mm=tolerances.within_mm)
        with timings.stage("3-D view"):
            deviations = {m: dev.vertex_deviation_mm for m in shown if (dev := reports[m].deviation) is not None}
            views_in_order = (input_view(bone.work.vertices, bone.work.faces, deviations,
                                         settings.analysis.view_max_triangles),
                              *(views[m] for m in shown))
        measured = None
        if frame.bone == "tibia":  # the parameters of ``bonecad measure`` are defined on a tibia
            with timings.stage("morphometry"):
                measured = measure_tibia(bone, frame, settings.morphometry).values()
        with timings.stage("report"):
            viewer = viewer_html(list(views_in_order), frame.as_dict())
            figures = {"curves": stage_dir / "curves.png", "histograms": histograms.result()}
            doc = ReportDocument(input_summary={**bone.summary(), "side": frame.side}, frame=frame.as_dict(),
                                 models=tuple(reports[m] for m in MODELS if m in reports),
                                 timings_s={**timings.seconds, "total (wall)": timings.wall_s()},
                                 tolerances=tolerances, contours=contours, figures=figures, viewer=viewer,
                                 morphometry=measured)
            export("report", doc, stage_dir)
    return Reconstruction(bone=bone, frame=frame, contours=contours,
                          models={m: built[m] for m in MODELS if m in built},
                          reports={m: reports[m] for m in MODELS if m in reports}, views=views_in_order)


def mesh_noise(bone: BoneMesh, frame: AnatomicalFrame, settings: Settings) -> MeshNoise:
    """The mesh's noise at the T-spline fit's points (local, mm) and its noise level (mm)."""
    from bonecad.tspline_model.model import mesh_noise as measure

    return measure(bone, frame, settings.tspline)


def curve_files_and_nurbs(contours: ContourSet, bone: BoneMesh, stage_dir: Path, settings: Settings,
                          nurbs: bool, pixels: tuple[Coverage, ...] | None = None
                          ) -> tuple[dict[str, float], tuple[object, ModelReport, ViewMesh] | None]:
    """curves.step, curves.iges, curves.png, then (``nurbs``) the NURBS model, its files, analysis and
    figures, all in this process (``pixels``: see :func:`analyse`). Returns (stage timings, (model, report) or
    None)."""
    from bonecad.nurbs_model.model import build_nurbs
    from bonecad.render.curves import curves_png

    timings = Timings()
    with timings.stage("curves to STEP, IGES and PNG"):
        export("curves", contours, stage_dir, only=["step", "iges"])
        curves_png(stage_dir / "curves.png", *bone_coordinates(bone, contours.frame), contours,
                   height_px=settings.analysis.figure_height_px)
    if not nurbs:
        return timings.seconds, None
    with timings.stage("NURBS model"):
        model = build_nurbs(contours, settings=settings.nurbs)
        export("nurbs", model, stage_dir)
    with timings.stage("NURBS analysis"):
        report, view = analyse("nurbs", model, bone, contours.frame, stage_dir, settings, model.summary(),
                               InProcess(), pixels)
    return timings.seconds, (model, report, view)


def analyse(name: str, model, bone: BoneMesh, frame: AnatomicalFrame, out_dir: Path, settings: Settings,
            info: dict, ex: Executor, pixels: tuple[Coverage, ...] | None = None) -> tuple[ModelReport, ViewMesh]:
    """Deviation, continuity and the figures ``{name}_deviation.png`` and ``{name}_zebra.png`` of one
    model, and its mesh for the 3-D view; zebra and continuity, the colour map and the view's mesh as
    background jobs. ``pixels``: the working copy's colour-map views (``render.figures.mesh_views``), shared
    by the models (None: the colour map rasterises the mesh itself)."""
    from bonecad.render.figures import deviation_map_png

    view_frame = frame.axes.T  # columns: lateral, anterior, proximal
    tess = tessellate_model(model.shape, settings.analysis)
    side = ex.submit(zebra_and_continuity, name, model, tess, out_dir, view_frame, settings)
    fairness = ex.submit(shape_fairness_of, model, frame, settings.analysis)
    view = ex.submit(model_view, name, tess.vertices, tess.triangles, tess.triangle_face, bone.work.locator,
                     settings.analysis.view_max_triangles)
    deviation = model_deviation(tess, bone, frame, settings.analysis)
    shown = bone.work  # the colour map draws the working copy (its vertices' deviations)
    colour_map = ex.submit(deviation_map_png, out_dir / f"{name}_deviation.png", shown.vertices, shown.faces,
                           deviation.vertex_deviation_mm, view_frame,
                           title=f"{name}: deviation of the mesh from the CAD model, mm",
                           height_px=settings.analysis.figure_height_px, pixels=pixels)
    zebra, (continuity, knots, folds) = side.result()
    figures = {"deviation": colour_map.result(), "zebra": zebra}
    report = ModelReport(name=name, info=info, deviation=deviation, continuity=continuity, knots=knots,
                         folds=folds, figures=figures, fairness=fairness.result())
    return report, view.result()


def shape_fairness_of(model, frame: AnatomicalFrame, settings: AnalysisSettings):
    """The fairness figure of a model's solid (a background job: the model pickles, the labels do not)."""
    return model_fairness(model.shape, frame, settings)


def zebra_and_continuity(name: str, model, tess, out_dir: Path, view_frame: np.ndarray, settings: Settings):
    """The zebra figure, and the seam and knot continuity and the folds, of a tessellated model."""
    from bonecad.render.figures import zebra_png

    zebra = zebra_png(out_dir / f"{name}_zebra.png", tess, view_frame, title=f"{name}: zebra (reflection lines)",
                      height_px=settings.analysis.figure_height_px)
    return zebra, model_continuity(model.shape, tess, list(model.face_names), settings.analysis)


def reconstruct(
    source: str | Path,
    out_dir: str | Path | None = None,
    settings: Settings | None = None,
    *,
    until: Until = "models",
    units: Units = "auto",
    executor: Executor | None = None,
    progress: FitProgress | None = None,
) -> Reconstruction:
    """The whole pipeline on a mesh file or CT volume; outputs in ``out_dir`` (a new temporary folder if
    None); ``settings`` default to the shipped ones (``Settings.load()``); ``progress``: see
    :func:`reconstruct_bone`."""
    settings = settings if settings is not None else Settings.load()
    timings = Timings()
    if out_dir is None:
        out_dir = Path(tempfile.mkdtemp(prefix="bonecad-"))
    with huge_pages(settings.pipeline.huge_pages):
        with timings.stage("input"):
            if until == "models" and executor is None:  # the analysis needs the full mesh's tree
                # (huge pages for the intake's large arrays, which reuse their memory; the cleanup's jobs in a thread,
                # which shares it, the working copy's forked: its simplifier keeps global state)
                background = settings.pipeline.background_jobs
                with (huge_pages(True), freed_memory_reused(), executor_for(background) as ex,
                      helper_thread(background) as beside):
                    bone = load_input(source, settings, units=units, working_copy=copy_beside_tree(ex),
                                      beside=beside)
            else:
                bone = load_input(source, settings, units=units)
        return reconstruct_bone(bone, out_dir, settings, until=until, timings=timings, executor=executor,
                                progress=progress)


def run_demo(out_dir: str | Path, settings: Settings | None = None, progress: FitProgress | None = None
             ) -> Reconstruction:
    """``bonecad demo``: the embedded phantom as a real case starts, from its CT, through every stage.

    Writes the phantom's mesh (phantom.stl) and its synthetic CT (0.8 mm voxels,
    30 HU noise) as NIfTI (phantom_ct.nii.gz) and as a DICOM series (phantom_ct/),
    then runs the pipeline on the DICOM series.
    """
    from bonecad.imaging import mesh_to_ct
    from bonecad.imaging.phantom_tibia import TibiaParameters, phantom_tibia
    from bonecad.imaging.volume import write_dicom_series, write_nifti

    settings = settings if settings is not None else Settings.load()
    timings = Timings()
    with huge_pages(settings.pipeline.huge_pages), staged_output(out_dir) as stage_dir:
        with timings.stage("phantom tibia and its CT"):
            phantom = phantom_tibia(TibiaParameters(), settings=settings.mesh, plausible=settings.units)
            phantom.to_trimesh().export(stage_dir / "phantom.stl")
            ct = mesh_to_ct(phantom.vertices, phantom.faces, voxel_mm=0.8)
            write_nifti(ct, stage_dir / "phantom_ct.nii.gz")
            dicom = write_dicom_series(ct, stage_dir / "phantom_ct")
        with timings.stage("segmentation of the phantom CT"):
            # named by where the series will be, not by the staging folder
            bone = replace(load_input(dicom, settings), source=str(Path(out_dir) / dicom.name))
        result = reconstruct_bone(bone, stage_dir, settings, timings=timings, progress=progress)
    return replace(result, out_dir=Path(out_dir))


def patch_region(settings: Settings, name: str | None, height_mm: tuple[float, float] | None,
                 angle_deg: tuple[float, float] | None):
    """The region of ``bonecad patch``: a named one of [patch], or the height and angle ranges given."""
    from bonecad.tspline_model.patch import PatchRegion

    if name is not None:
        if height_mm is not None or angle_deg is not None:
            raise InputError("give either --region NAME or --height and --angle, not both")
        presets = {k: v for k, v in vars(settings.patch).items() if isinstance(v, tuple)}
        if name not in presets:
            raise InputError(f"no region named {name!r}; the named regions are {sorted(presets)}")
        h0, h1, a0, a1 = presets[name]
        return PatchRegion(name, (h0, h1), (a0, a1))
    if height_mm is None or angle_deg is None:
        raise InputError("give --region NAME, or both --height FROM TO and --angle FROM TO")
    return PatchRegion("patch", (height_mm[0], height_mm[1]), (angle_deg[0], angle_deg[1]))


def _model_folder(folder: Path, mesh: Path | None, settings: Settings):
    """The tube (bone coordinates), the frame's axes and origin, the mesh and the bone's name of a
    reconstruction's folder (tspline.json, frame.json; the mesh named in frame.json unless ``mesh`` is given)."""
    import json

    from bonecad.splines.tspline import from_dict

    try:
        model = json.loads((folder / "tspline.json").read_text())
        frame = json.loads((folder / "frame.json").read_text())
        tube = from_dict(model["tube"])
        bone_frame = frame["bone_frame"]
        rounded = np.array([bone_frame["lateral"], bone_frame["anterior"], bone_frame["proximal"]], dtype=np.float64)
        # frame.json rounds to 1e-6: the nearest orthogonal axes, so that mapping the tube to bone
        # coordinates and the patch back is exact (rounded axes would move it by ~1e-5 mm)
        left, _, right = np.linalg.svd(rounded)
        axes = left @ right
        origin = np.array(bone_frame["origin"], dtype=np.float64)
        source = Path(mesh or frame["input"]["file"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"not a bonecad reconstruction folder (tspline.json and frame.json): {exc}", folder) from exc
    if not source.exists():
        raise InputError(f"the mesh of this reconstruction, {source}, is gone: give it with --mesh", folder)
    bone = load_bone(source, settings=settings.mesh, plausible=settings.units,
                     keep=load_profile(frame.get("bone", "tibia")).body)
    tube = tube.with_control_points((tube.control_points - origin) @ axes.T, tube.weights)
    return tube, axes, origin, bone, frame.get("bone", "tibia")  # a tibia's frame.json names no bone


def _check_region_on(bone: str, region, settings: Settings, source: Path) -> None:
    """InputError when ``region`` is a named region that is not on this bone (its profile lists them)."""
    named = load_profile(bone).patch_regions
    if region.name in vars(settings.patch) and region.name not in named:
        raise InputError(f"region {region.name!r} is not on a {bone}; the {bone}'s named regions are {list(named)} "
                         "(or give --height and --angle)", source)


def _surface_of(source: Path, settings: Settings, region, *, mesh: Path | None, units: Units):
    """The tube (bone coordinates), the frame's axes and origin, the bone mesh, the bone's settings and the
    heights (mm, bone coordinates) of the apices where the frame's axis leaves the bone (distal, proximal) of a
    reconstruction's folder or an input, for which the T-spline is built; InputError if ``region`` is a
    named region not on this bone."""
    import json

    from bonecad.tspline_model.model import build_tspline_model

    if source.is_dir() and (source / "tspline.json").exists():
        tube, axes, origin, bone, name = _model_folder(source, mesh, settings)
        _check_region_on(name, region, settings, source)
        apices = json.loads((source / "frame.json").read_text())["apices"]
        ends = [np.asarray(apices[end], dtype=np.float64) for end in ("distal", "proximal")]
        return tube, axes, origin, bone, settings, tuple(
            float(((p - origin) @ axes.T)[2]) for p in ends)
    bone = load_input(source, settings, units=units)
    settings = bone_settings(bone, settings)
    _check_region_on(settings.pipeline.bone, region, settings, source)
    frame, contours, _ = frame_and_contours(bone, settings)
    model = build_tspline_model(bone, frame, contours, settings=settings.tspline,
                                apex_hole_radius_mm=settings.curves.apex_hole_radius_mm)
    joints = tuple(float(frame.to_bone(p[None])[0, 2]) for p in (frame.distal_apex, frame.proximal_apex))
    return model.tspline, frame.axes, frame.origin, bone, settings, joints


def run_patch(source: str | Path, out_dir: str | Path, settings: Settings, region, *, mesh: Path | None = None,
              units: Units = "auto"):
    """``bonecad patch``: one region of the T-spline surface as one untrimmed B-spline face.

    source : a reconstruction's output folder (its tspline.json, frame.json and mesh), or an input
    (mesh file or CT volume), for which the T-spline model is built first. Writes patch.step,
    patch.iges and patch.json into ``out_dir``; returns the PatchDocument.
    """
    from bonecad.export.documents import PatchDocument
    from bonecad.occ.operations import solids, thicken
    from bonecad.occ.brep import is_valid, volume_mm3
    from bonecad.occ.surfaces import make_face
    from bonecad.tspline_model.patch import footprint_patch, mesh_deviation

    tube, axes, origin, bone, settings, _ = _surface_of(Path(source), settings, region, mesh=mesh, units=units)
    footprint = footprint_patch(tube, region)
    doc = PatchDocument(footprint, axes, origin, {}, {})
    deviation = mesh_deviation(doc.surface, bone.vertices, bone.faces, settings.patch.mesh_samples)
    thickness = settings.patch.plate_thickness_mm
    blank = solids(thicken(make_face(doc.surface), thickness))
    plate = {"thickness_mm": thickness, "direction": "out of the bone", "solids": len(blank),
             "valid": bool(blank) and all(map(is_valid, blank)),
             "volume_mm3": round(sum(volume_mm3(b) for b in blank), 3)}
    doc = replace(doc, mesh_deviation=deviation, plate_blank=plate)
    with staged_output(Path(out_dir)) as stage_dir:
        export("patch", doc, stage_dir)
    return doc


def read_reduction(path: Path):
    """The main fragments and fracture heights of a ``bonecad reduce`` folder's reduction.json (or that file):
    ``{"fragments": [{"name": str, "height_mm": [from, to]}, ...], "fracture_heights_mm": [h, ...]}``, heights
    along the frame's axis in mm above its origin; without fracture_heights_mm, the middles between
    consecutive fragments."""
    import json

    from bonecad.tspline_model.plate import Fragment

    file = path / "reduction.json" if path.is_dir() else path
    try:
        data = json.loads(file.read_text())
        fragments = tuple(Fragment(str(f["name"]), (float(f["height_mm"][0]), float(f["height_mm"][1])))
                          for f in data["fragments"])
        ordered = sorted(fragments, key=lambda f: f.height_mm[0])
        lines = data.get("fracture_heights_mm") or [0.5 * (a.height_mm[1] + b.height_mm[0])
                                                    for a, b in zip(ordered, ordered[1:])]
        heights = tuple(float(h) for h in lines)
    except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
        raise InputError(f"not a reduction (reduction.json with fragments and their height_mm): {exc}", file) from exc
    if len(fragments) < 2:
        raise InputError(f"a fracture needs two main fragments or more, the reduction lists {len(fragments)}", file)
    return fragments, heights


def run_plate(source: str | Path, out_dir: str | Path, settings: Settings, region, *, mesh: Path | None = None,
              units: Units = "auto", fracture: Path | None = None):
    """``bonecad plate``: a fixation plate on ``region`` of the bone's T-spline surface, its screws and fit.

    source : a reconstruction's output folder or an input (mesh file or CT volume), as for ``run_patch``.
    Writes plate.step/.iges/.stl, plate_curves.step, screws.csv, plate.json and plate.png into ``out_dir``
    (all or nothing); returns the PlateDocument. ``fracture``: a reduction (:func:`read_reduction`) whose
    fragments the screws must hold (the plate keeps every hole; screws near a fracture line are left out).
    """
    from bonecad.export.plate import PlateDocument
    from bonecad.occ.plate import check_plate, plate_solid
    from bonecad.render.plate import plate_png
    from bonecad.tspline_model.patch import footprint_patch
    from bonecad.errors import KernelError
    from bonecad.mesh.closest import TriangleLocator
    from bonecad.tspline_model.plate import fixation, plan_plate, plate_face

    timings = Timings()
    with timings.stage("model"):
        tube, axes, origin, bone, settings, joints = _surface_of(Path(source), settings, region, mesh=mesh,
                                                                 units=units)
    with timings.stage("plan"):
        footprint = footprint_patch(tube, plate_face(region, settings.plate))
        vertices = (bone.vertices - origin) @ axes.T
        faces = bone.faces[:, ::-1] if np.linalg.det(axes) < 0 else bone.faces  # outward in mirrored coordinates
        locator = TriangleLocator(vertices, faces)
    for smoothing in (None, *settings.plate.underside_smoothing_mm):  # the exact underside, then smoothed ones
        with timings.stage("plan"):
            plan = plan_plate(footprint, vertices, faces, joints, settings.plate, locator, smoothing_mm=smoothing)
        with timings.stage("solid"):
            # the underside's surface in scanner coordinates, its parameters kept (S_u x S_v turns with a mirror)
            surface = replace(plan.underside, poles=plan.underside.poles @ axes + origin)
            outward = plan.outward * float(np.sign(np.linalg.det(axes)))
            holes = [(s.underside @ axes + origin, s.direction @ axes) for s in plan.screws]
            try:
                solid, _ = plate_solid(surface, plan.outline_uv, plan.offset_mm, outward,
                                       settings.plate.thickness_mm, holes, settings.plate.hole_diameter_mm)
                break
            except KernelError as exc:
                log.warning("the plate on %s: %s", "the exact underside" if smoothing is None
                            else f"an underside smoothed at {smoothing:g} mm", exc)
    else:
        raise KernelError("no valid plate solid on the exact or any smoothed underside ([plate] "
                          "underside_smoothing_mm)")
    check = check_plate(solid)
    fixed = None
    if fracture is not None:
        fragments, lines = read_reduction(Path(fracture))
        fixed = fixation(plan, fragments, lines, settings.plate.screws_per_fragment, settings.plate.fracture_margin_mm)
        plan = replace(plan, screws=fixed.screws)
    doc = PlateDocument(region, plan, axes, origin, solid, check, dict(timings.seconds), fixed)
    with staged_output(Path(out_dir)) as stage_dir:
        export("plate", doc, stage_dir)
        plate_png(stage_dir / "plate.png", plan, vertices, f"{region.name}: {len(plan.screws)} holes, "
                  f"{settings.plate.thickness_mm:g} mm thick, gap {settings.plate.gap_mm:g} mm")
    return doc
