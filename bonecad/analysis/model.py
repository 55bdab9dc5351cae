"""Analyse one CAD model of a bone: deviation both ways, seam and knot continuity, figures.

The glue between a model stage and the report: regions come from the
anatomical frame, views from its axes, and every figure is written into the
caller's (staged) output folder.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bonecad.anatomy.frame import AnatomicalFrame
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.run.executor import JobGroup
from bonecad.analysis.continuity import KnotContinuity, SeamContinuity, knot_continuity, seam_continuity
from bonecad.analysis.deviation import DeviationResult, shape_deviation
from bonecad.render.figures import deviation_map_png, histogram_png, zebra_png
from bonecad.occ.tessellate import tessellate

log = logging.getLogger("bonecad")


@dataclass(frozen=True)
class ModelReport:
    """Everything the report says about one CAD model.

    figures : name -> PNG path (copied by name into the report folder's references)
    """

    name: str
    info: dict[str, Any] = field(default_factory=dict)
    deviation: DeviationResult | None = None
    continuity: SeamContinuity | None = None
    knots: list[KnotContinuity] | None = None
    figures: dict[str, Path] = field(default_factory=dict)


def region_labels(frame: AnatomicalFrame):
    """A function labelling scanner points 'distal', 'shaft' or 'proximal' by their height on the axis."""

    def labels(points: np.ndarray) -> np.ndarray:
        height = frame.to_bone(points)[:, 2]
        out = np.full(len(points), "shaft", dtype=object)
        out[height < frame.distal_boundary_mm] = "distal"
        out[height > frame.proximal_boundary_mm] = "proximal"
        return out

    return labels


def analyse_model(
    name: str,
    shape,
    bone: BoneMesh,
    frame: AnatomicalFrame,
    out_dir: Path,
    *,
    info: dict,
    sample_points: int | None = None,
    face_names: list[tuple[str, object]] | None = None,
    jobs: JobGroup | None = None,
) -> ModelReport:
    """Deviation, continuity and figures (``{name}_deviation.png``, ``{name}_histogram.png``,
    ``{name}_zebra.png``) of ``shape`` (a TopoDS_Shape in scanner mm) against ``bone``.

    face_names : (name, TopoDS_Face) of the faces, as the model names them:
    the continuity is then also counted per pair of face names.
    jobs : a group of background jobs (``bonecad.run.executor``): the zebra figure
    and the continuity are then made on the second core while the deviation is
    measured here, and the colour map while the histogram is drawn; None: all
    in this process.
    """
    view_frame = frame.axes.T  # columns: lateral, anterior, proximal
    tess = tessellate(shape)
    zebra_path = out_dir / f"{name}_zebra.png"
    title = f"{name}: zebra (reflection lines)"
    args = (shape, tess, zebra_path, view_frame, title, face_names)
    side = None if jobs is None else jobs.start(_zebra_and_continuity, *args)
    deviation = shape_deviation(
        bone.vertices, bone.faces, shape, regions=region_labels(frame), sample_points=sample_points, tessellation=tess
    )
    map_args = (out_dir / f"{name}_deviation.png", bone.vertices, bone.faces, deviation.vertex_deviation_mm,
                view_frame)
    map_title = f"{name}: deviation of the mesh from the CAD model, mm"
    map_job = None if jobs is None else jobs.start(deviation_map_png, *map_args, title=map_title)
    histogram = histogram_png(
        out_dir / f"{name}_histogram.png",
        {"whole bone": deviation.mesh_to_cad.histogram, **deviation.mesh_to_cad.region_histograms},
        title=f"{name}: share of surface per deviation band",
    )
    colour_map = deviation_map_png(*map_args, title=map_title) if map_job is None else map_job.result()[0]
    zebra, continuity, knots = _zebra_and_continuity(*args) if side is None else side.result()[0]
    figures = {"deviation": colour_map, "histogram": histogram, "zebra": zebra}
    stats = deviation.mesh_to_cad.stats
    log.info("%s: RMS %.3f mm, worst %.3f mm outside, %.3f mm inside", name, stats.rms_mm, stats.max_outside_mm,
             stats.max_inside_mm)
    return ModelReport(name=name, info=info, deviation=deviation, continuity=continuity, knots=knots, figures=figures)


def _zebra_and_continuity(shape, tess, path: Path, view_frame: np.ndarray, title: str, face_names):
    """The zebra figure, the seam continuity and the knot continuity of a tessellated shape."""
    return (zebra_png(path, tess, view_frame, title=title),
            seam_continuity(shape, tessellation=tess, face_names=face_names), knot_continuity(shape))
