"""Stage 6: analyse one CAD model of a bone: deviation both ways, seam and knot continuity.

Pure: it reads the model's solid and the bone, and returns figures (no files;
the runner renders and writes them). Regions come from the anatomical frame.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bonecad.analysis.deviation import DeviationResult, shape_deviation
from bonecad.analysis.folds import FoldCheck, shape_folds
from bonecad.analysis.fairness import Fairness, shape_fairness
from bonecad.analysis.statistics import settings_band_edges
from bonecad.anatomy.frame import AnatomicalFrame
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.mesh.closest import TriangleLocator
from bonecad.analysis.continuity import (ContinuityTolerances, KnotContinuity, SeamContinuity, knot_continuity,
                                         seam_continuity)
from bonecad.mesh.tessellation import Tessellation, TessellationSettings
from bonecad.settings import AnalysisSettings

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ModelReport:
    """Everything the report says about one CAD model.

    figures : name -> PNG path (copied by name into the report folder's references)
    folds : the elements of its faces whose normal reverses (``analysis.folds``), or None (not checked)
    """

    name: str
    info: dict[str, Any] = field(default_factory=dict)
    deviation: DeviationResult | None = None
    continuity: SeamContinuity | None = None
    knots: list[KnotContinuity] | None = None
    figures: dict[str, Path] = field(default_factory=dict)
    folds: FoldCheck | None = None
    fairness: Fairness | None = None


def region_labels(frame: AnatomicalFrame):
    """A function labelling scanner points 'distal', 'shaft' or 'proximal' by their height on the axis."""

    def labels(points: np.ndarray) -> np.ndarray:
        height = frame.to_bone(points)[:, 2]
        out = np.full(len(points), "shaft", dtype=object)
        out[height < frame.distal_boundary_mm] = "distal"
        out[height > frame.proximal_boundary_mm] = "proximal"
        return out

    return labels


def tessellation_settings(settings: AnalysisSettings) -> TessellationSettings:
    """The tessellation tolerances of the [analysis] settings."""
    return TessellationSettings(
        deflection_mm=settings.tessellation_deflection_mm,
        angular_deflection_rad=settings.tessellation_angular_deflection_rad,
        coverage_tolerance=settings.coverage_tolerance,
        area_rel_eps=settings.area_rel_eps,
        max_edge_mm=settings.tessellation_max_edge_mm,
        small_face_factor=settings.small_face_shortfall_factor,
    )


def continuity_tolerances(settings: AnalysisSettings) -> ContinuityTolerances:
    """The seam-class thresholds of the [analysis] settings."""
    return ContinuityTolerances(
        gap_mm=settings.continuity_gap_mm,
        angle_deg=settings.continuity_angle_deg,
        curvature_jump=settings.continuity_curvature_jump,
        curvature_radius_ref_mm=settings.continuity_curvature_radius_ref_mm,
    )


def tessellate_model(shape, settings: AnalysisSettings) -> Tessellation:
    """The model's tessellation (scanner mm), shared by the deviation, the continuity and the figures."""
    from bonecad.occ.tessellate import tessellate

    return tessellate(shape, tessellation_settings(settings))


def model_deviation(tess: Tessellation, bone: BoneMesh, frame: AnatomicalFrame,
                    settings: AnalysisSettings) -> DeviationResult:
    """Signed deviation between the bone mesh (the full mesh) and the model, both ways, overall and per region;
    the colour map's at the vertices of its working copy (``BoneMesh.work``)."""
    faces = bone.faces
    locator: TriangleLocator | None = bone.locator
    if bone.extra.get("excluded_centres") is not None:  # a reduced fracture: its fracture surfaces are not bone
        from scipy.spatial import cKDTree

        centres = bone.vertices[faces].mean(axis=1)
        near = cKDTree(bone.extra["excluded_centres"]).query(centres, distance_upper_bound=bone.extra["excluded_mm"])
        faces, locator = faces[~np.isfinite(near[0])], None
    deviation = shape_deviation(bone.vertices, faces, tess, regions=region_labels(frame),
                                sample_points=settings.sample_points, edges_mm=settings_band_edges(settings),
                                map_vertices=bone.work.vertices, mesh_locator=locator)
    stats = deviation.mesh_to_cad.stats
    log.info("RMS %.3f mm, worst %.3f mm outside, %.3f mm inside", stats.rms_mm, stats.max_outside_mm,
             stats.max_inside_mm)
    return deviation


def model_continuity(shape, tess: Tessellation, face_names, settings: AnalysisSettings
                     ) -> tuple[SeamContinuity, list[KnotContinuity], FoldCheck]:
    """Seam classes of every shared edge (counted per pair of face names), the knot continuity and the
    elements whose normal reverses (``analysis.folds``)."""
    seams = seam_continuity(shape, tessellation=tess, face_names=face_names,
                            tolerances=continuity_tolerances(settings))
    return seams, knot_continuity(shape), shape_folds(shape, face_names)


def model_fairness(shape, frame: AnatomicalFrame, settings: AnalysisSettings) -> Fairness:
    """The fairness figure of a model's exact faces, overall and per region (``analysis.fairness``)."""
    fairness = shape_fairness(shape, step_mm=settings.fairness_step_mm, labels=region_labels(frame))
    log.info("fairness: curvature variation %.4g /mm^2 (%s)", fairness.curvature_variation,
             ", ".join(f"{k} {v:.4g}" for k, v in fairness.regions.items()))
    return fairness
