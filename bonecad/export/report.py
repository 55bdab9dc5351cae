"""``report.json`` and ``report.html``: the analysis results of one run, for people and scripts.

report.json schema (``"schema": "bonecad.report/1"``)::

    {
      "schema": "bonecad.report/1",
      "input":   {...},          # caller's input summary (file, triangles, units, side, ...)
      "frame":   {...},          # caller's anatomical frame (origin, axes, ...)
      "timings_s": {stage: seconds},
      "models": {
        NAME: {                  # "nurbs", "tspline", ...
          "info": {...},         # caller's figures: "faces", "control_points", ...
          "deviation": {         # DeviationResult.to_dict(), or null
            "sign_convention": "positive = mesh outside the CAD model",
            "mesh_to_cad" | "cad_to_mesh": {
              "samples", "refined_share",
              "stats": {"rms_mm", "mean_mm", "abs_percentiles_mm": {"p50", "p90", "p95", "p99", "p99.9"},
                        "max_outside_mm", "max_inside_mm", "area_mm2", "count"},
              "histogram": {"edges_mm": [B+1], "shares": [B+2: underflow, bands, overflow]},
              "regions": {REGION: {"stats": ..., "histogram": ...}}},
            "unrefined_bound_mm", "timings_s"},
          "continuity": {"summary": {...}, "edges": [...]} or null,   # SeamContinuity.to_dict()
          "knots": [KnotContinuity.to_dict(), ...] or null,
          "figures": {name: file name relative to the report}   # "deviation", "zebra"
        }
      },
      "figures": {name: file name relative to the report},   # the run's: "curves", "histograms"
      "comparison": [ {row}, ... ] or null,  # when models "nurbs" and "tspline" both exist
      "tolerances": {"share", "within_mm", "max_deviation_mm", "rms_mm"} or null,   # the run's [tspline]
      "summary": {NAME: {"verdict": "met" | "not met" | "stopped at the data's noise" | "not measured",
                         "reason", "checks": [{"check", "measured", "target", "met"}],
                         "faces", "control_points", "within_mm": {"0.1": share, ...},
                         "max_mm": {"mesh_to_cad", "cad_to_mesh"}, "rms_mm": {...},
                         "seam_classes": {"gap", "C0", "G1", "G2"},
                         "folds": {"elements", "reversed_elements", "where": [{"face", "centre_mm",
                                   "largest_turn_deg"}]} or null, "files_bytes": {file name: bytes}}},
      "contours": [{"region", "curves", "control_points_per_curve", "tolerance_mm",
                    "worst_max_deviation_mm", "mean_rms_deviation_mm", "within_tolerance", "repairs"}] or null,
      "morphometry": {parameter: value (mm, degrees; `bonecad measure`'s PARAMETERS)} or null
    }

report.html (``bonecad.export.report_page``) shows the same for people: the
summary first (input, one card per model with its verdict), the interactive
3-D view, then tables (never a raw list or dict in a cell) and every figure
embedded (base64 PNG).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bonecad.export.registry import exporter
from bonecad.staging import staged_file
from bonecad.analysis.continuity import CLASSES, SeamContinuity
from bonecad.analysis.model import ModelReport
from bonecad.contours.curves import ContourSet
from bonecad.export.report_page import render_html
from bonecad.settings import TSplineSettings

SCHEMA = "bonecad.report/1"
#: share-within limits shown in the comparison table (mm)
WITHIN_MM = (0.1, 0.25, 0.5, 1.0)


def _all_control_points(info: dict) -> int | None:
    """A model's control points with those of its apex caps (the T-spline counts them apart)."""
    if info.get("control_points") is None:
        return None
    return int(info["control_points"]) + int(info.get("cap_control_points") or 0)


def _worst_away_from_caps(continuity: SeamContinuity | None) -> str | None:
    """The worst seam class among seams that touch no apex cap face (None without names)."""
    if continuity is None or continuity.face_names is None:
        return None
    away = np.array(["apex_cap" not in pair for pair in continuity.pair_names()], dtype=bool)
    classes = set(continuity.classes[away].tolist())
    return next((name for name in CLASSES if name in classes), "G2") if away.any() else "none"


def _plain(value):
    """JSON-ready copy: numpy scalars/arrays to Python, paths to strings."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def comparison_rows(models: list[ModelReport]) -> list[dict[str, Any]] | None:
    """NURBS-versus-T-spline rows (None unless both 'nurbs' and 'tspline' are present)."""
    by_name = {m.name: m for m in models}
    if not {"nurbs", "tspline"} <= set(by_name):
        return None
    rows = []
    rows.append({"quantity": "faces", **{n: by_name[n].info.get("faces") for n in ("nurbs", "tspline")}})
    rows.append({"quantity": "control points (all faces, apex caps included)",
                 **{n: _all_control_points(by_name[n].info) for n in ("nurbs", "tspline")}})
    rows.append(
        {
            "quantity": "continuity class (worst seam)",
            **{
                n: (cont.summary()["worst_class"] if (cont := by_name[n].continuity) else None)
                for n in ("nurbs", "tspline")
            },
        }
    )
    rows.append(
        {
            "quantity": "continuity class (worst seam away from the apex caps)",
            **{n: _worst_away_from_caps(by_name[n].continuity) for n in ("nurbs", "tspline")},
        }
    )
    for limit in WITHIN_MM:
        rows.append(
            {
                "quantity": f"surface within {limit:g} mm",
                **{
                    n: (dev.mesh_to_cad.share_within(limit) if (dev := by_name[n].deviation) else None)
                    for n in ("nurbs", "tspline")
                },
            }
        )
    for key, label in (("rms_mm", "RMS deviation, mm"),):
        rows.append(
            {
                "quantity": label,
                **{
                    n: (getattr(dev.mesh_to_cad.stats, key) if (dev := by_name[n].deviation) else None)
                    for n in ("nurbs", "tspline")
                },
            }
        )
    return rows


@dataclass(frozen=True)
class Tolerances:
    """The run's surface tolerances (``[tspline]``): at least ``share`` of the surface within
    ``within_mm`` (mm), no point farther than ``max_deviation_mm``, RMS at most ``rms_mm`` (mm)."""

    share: float
    within_mm: float
    max_deviation_mm: float
    rms_mm: float

    @classmethod
    def of(cls, settings: TSplineSettings) -> Tolerances:
        share, within = settings.target_share_within_mm
        return cls(float(share), float(within), settings.max_deviation_mm, settings.rms_mm)

    def to_dict(self) -> dict[str, float]:
        return {"share": self.share, "within_mm": self.within_mm, "max_deviation_mm": self.max_deviation_mm,
                "rms_mm": self.rms_mm}


#: verdicts of a model against the run's tolerances
MET, NOT_MET, AT_NOISE, NOT_MEASURED = "met", "not met", "stopped at the data's noise", "not measured"


def verdict(model: ModelReport, tolerances: Tolerances) -> dict[str, Any]:
    """The model against the tolerances, measured by the analysis in both directions: the mesh near the
    model (mesh -> CAD) and the model near the mesh (CAD -> mesh, where a fold shows), and no element whose
    normal reverses (``analysis.folds``).

    "met" when every check holds; otherwise "stopped at the data's noise" when the model's fit stopped
    there (its ``fit_stopped`` says so, and is the reason) and the model does not fold, else "not met"."""
    if model.deviation is None:
        return {"verdict": NOT_MEASURED, "reason": "no deviation was measured", "checks": []}
    t = tolerances
    checks = []
    for label, d in (("mesh to CAD", model.deviation.mesh_to_cad), ("CAD to mesh", model.deviation.cad_to_mesh)):
        worst = max(d.stats.max_outside_mm, d.stats.max_inside_mm)
        share = d.share_within(t.within_mm)
        checks += [
            {"check": f"{label}: share of the surface within {t.within_mm:g} mm", "measured": share,
             "target": f">= {t.share:g}", "met": share >= t.share},
            {"check": f"{label}: largest deviation, mm", "measured": worst, "target": f"<= {t.max_deviation_mm:g}",
             "met": worst <= t.max_deviation_mm},
            {"check": f"{label}: RMS deviation, mm", "measured": d.stats.rms_mm, "target": f"<= {t.rms_mm:g}",
             "met": d.stats.rms_mm <= t.rms_mm},
        ]
    if model.folds is not None:
        checks.append({"check": "elements whose normal reverses (folds)", "measured": model.folds.reversed_elements,
                       "target": "= 0", "met": model.folds.reversed_elements == 0})
    missed = [c for c in checks if not c["met"]]
    if not missed:
        return {"verdict": MET, "reason": "every tolerance holds on the measured deviation, both ways, and the "
                "model does not fold", "checks": checks}
    stopped = str(model.info.get("fit_stopped") or "")
    misses = "; ".join(f"{c['check']} {c['measured']:.4g} (target {c['target']})" for c in missed)
    folded = model.folds is not None and model.folds.reversed_elements > 0
    if "noise" in stopped and not folded:
        return {"verdict": AT_NOISE, "reason": f"{misses}; the fit stopped: {stopped}", "checks": checks}
    return {"verdict": NOT_MET, "reason": misses + (f"; the fit stopped: {stopped}" if stopped else ""),
            "checks": checks}


def model_summary(model: ModelReport, tolerances: Tolerances | None, out_dir: Path | None) -> dict[str, Any]:
    """One model's summary card: verdict, counts, shares within :data:`WITHIN_MM`, max and RMS both
    ways (mm), seam classes and the sizes of its files in ``out_dir`` (bytes)."""
    dev = model.deviation
    card: dict[str, Any] = verdict(model, tolerances) if tolerances else {"verdict": NOT_MEASURED,
                                                                          "reason": "no tolerances", "checks": []}
    card["faces"] = model.info.get("faces")
    card["control_points"] = _all_control_points(model.info)
    directions = {"mesh_to_cad": dev.mesh_to_cad, "cad_to_mesh": dev.cad_to_mesh} if dev else {}
    card["within_mm"] = {f"{limit:g}": dev.mesh_to_cad.share_within(limit) for limit in WITHIN_MM} if dev else {}
    card["max_mm"] = {k: max(v.stats.max_outside_mm, v.stats.max_inside_mm) for k, v in directions.items()}
    card["rms_mm"] = {k: v.stats.rms_mm for k, v in directions.items()}
    card["seam_classes"] = model.continuity.summary()["class_counts"] if model.continuity else {}
    card["folds"] = model.folds.to_dict() if model.folds else None
    files = sorted(out_dir.glob(f"{model.name}.*")) if out_dir is not None else []
    card["files_bytes"] = {p.name: p.stat().st_size for p in files if p.is_file()}
    return card


def fairness_card(model: ModelReport) -> dict[str, Any]:
    """The summary card's fairness entry: the RMS of the gradient of mean curvature (1/mm^2) overall and
    per region, and its area-weighted median (``analysis.fairness``; None when not measured)."""
    f = model.fairness
    return {"fairness": None if f is None else {"curvature_variation_per_mm2": round(f.curvature_variation, 6),
                                                "regions": {k: round(v, 6) for k, v in f.regions.items()},
                                                "typical_per_mm2": round(f.typical, 6)}}


def contour_rows(contours: ContourSet) -> list[dict[str, Any]]:
    """Per region: curves, control points per curve, tolerance and achieved deviation (mm), repairs."""
    rows = []
    for region, s in contours.summary().items():
        rows.append({"region": region, **s,
                     "repairs": sum(len(c.repairs) for c in contours.region(region))})
    return rows


def build_report(
    *,
    input_summary: dict[str, Any],
    frame: dict[str, Any],
    models: list[ModelReport],
    timings_s: dict[str, float],
    tolerances: Tolerances | None = None,
    contours: ContourSet | None = None,
    figures: dict[str, Path] | None = None,
    out_dir: Path | None = None,
    morphometry: dict[str, float] | None = None,
) -> dict[str, Any]:
    """The report.json content (see module doc for the schema); file sizes are those in ``out_dir``."""
    names = [m.name for m in models]
    if len(set(names)) != len(names):
        raise ValueError(f"model names must be unique, got {names}")
    out_models = {}
    for m in models:
        out_models[m.name] = {
            "info": m.info,
            "deviation": m.deviation.to_dict() if m.deviation else None,
            "continuity": m.continuity.to_dict() if m.continuity else None,
            "knots": [k.to_dict() for k in m.knots] if m.knots is not None else None,
            "figures": {k: Path(v).name for k, v in m.figures.items()},
            "fairness": m.fairness.to_dict() if m.fairness else None,
        }
    return _plain(
        {
            "schema": SCHEMA,
            "input": input_summary,
            "frame": frame,
            "timings_s": timings_s,
            "models": out_models,
            "figures": {k: Path(v).name for k, v in (figures or {}).items()},
            "comparison": comparison_rows(models),
            "tolerances": tolerances.to_dict() if tolerances else None,
            "summary": {m.name: {**model_summary(m, tolerances, out_dir), **fairness_card(m)} for m in models},
            "contours": contour_rows(contours) if contours is not None else None,
            "morphometry": morphometry,
        }
    )


@dataclass(frozen=True)
class ReportDocument:
    """What the report holds: the input summary (file, bodies, side), the frame (``as_dict``), one
    ``ModelReport`` per model, the run's stage timings (s), the run's tolerances, the contour curves,
    the run's own figures (name -> PNG: the curve plan, the overlaid histograms) and the 3-D view's HTML
    (``bonecad.export.viewer.viewer_html``; empty: no view)."""

    input_summary: dict[str, Any]
    frame: dict[str, Any]
    models: tuple[ModelReport, ...]
    timings_s: dict[str, float]
    tolerances: Tolerances | None = None
    contours: ContourSet | None = None
    figures: dict[str, Path] = field(default_factory=dict)
    viewer: str = ""
    morphometry: dict[str, float] | None = None  # the tibia's parameters (``bonecad measure``), mm and degrees

    def build(self, out_dir: Path | None = None) -> dict[str, Any]:
        """The report.json content; ``out_dir``: the folder whose model files the summary sizes."""
        for owner, figures in [("the run", self.figures), *((f"model '{m.name}'", m.figures) for m in self.models)]:
            for fig_name, path in figures.items():
                if not Path(path).is_file():
                    raise FileNotFoundError(f"figure '{fig_name}' of {owner} is missing: {path}")
        return build_report(input_summary=self.input_summary, frame=self.frame, models=list(self.models),
                            timings_s=self.timings_s, tolerances=self.tolerances, contours=self.contours,
                            figures=self.figures, out_dir=out_dir, morphometry=self.morphometry)


@exporter("report", "json")
def report_json(doc: ReportDocument, out_dir: Path) -> Path:
    """report.json (schema above); figures referred to by file name (they are expected beside it)."""
    path = out_dir / "report.json"
    with staged_file(path) as tmp:
        tmp.write_text(json.dumps(doc.build(out_dir), indent=1, allow_nan=False) + "\n")
    return path


@exporter("report", "html")
def report_html(doc: ReportDocument, out_dir: Path) -> Path:
    """report.html: the same for people, summary first, with the 3-D view and every figure embedded."""
    path = out_dir / "report.html"
    with staged_file(path) as tmp:
        tmp.write_text(render_html(doc.build(out_dir), {"": doc.figures, **{m.name: m.figures for m in doc.models}},
                                   doc.viewer))
    return path
