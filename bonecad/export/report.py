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
          "figures": {name: file name relative to the report}
        }
      },
      "comparison": [ {row}, ... ] or null   # when models "nurbs" and "tspline" both exist
    }

report.html shows the same, with every figure embedded (base64 PNG), and the
NURBS-versus-T-spline table when both models exist.
"""
from __future__ import annotations

import base64
import html
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bonecad.export.registry import exporter
from bonecad.staging import staged_file
from bonecad.analysis.continuity import CLASSES, SeamContinuity
from bonecad.analysis.model import ModelReport

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


def build_report(
    *,
    input_summary: dict[str, Any],
    frame: dict[str, Any],
    models: list[ModelReport],
    timings_s: dict[str, float],
) -> dict[str, Any]:
    """The report.json content (see module doc for the schema)."""
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
        }
    return _plain(
        {
            "schema": SCHEMA,
            "input": input_summary,
            "frame": frame,
            "timings_s": timings_s,
            "models": out_models,
            "comparison": comparison_rows(models),
        }
    )


def _fmt(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    return html.escape(str(value))


def _table(rows: list[dict], columns: list[str]) -> str:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in columns)
    body = "".join("<tr>" + "".join(f"<td>{_fmt(r.get(c))}</td>" for c in columns) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def render_html(report: dict[str, Any], figures: dict[str, dict[str, Path]]) -> str:
    """report.html text; ``figures`` maps model -> figure name -> PNG path (embedded)."""
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>bonecad report</title>",
        "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;margin:1em 0}"
        "td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}th{background:#eee}"
        "img{max-width:100%;border:1px solid #ddd}</style></head><body>",
        "<h1>bonecad report</h1>",
        "<h2>Input</h2>",
        _table([{"key": k, "value": v} for k, v in report["input"].items()], ["key", "value"]),
        "<h2>Frame</h2>",
        _table([{"key": k, "value": v} for k, v in report["frame"].items()], ["key", "value"]),
    ]
    if report.get("comparison"):
        parts += ["<h2>NURBS versus T-spline</h2>", _table(report["comparison"], ["quantity", "nurbs", "tspline"])]
    for name, model in report["models"].items():
        parts.append(f"<h2>Model: {html.escape(name)}</h2>")
        parts.append(_table([{"key": k, "value": v} for k, v in model["info"].items()], ["key", "value"]))
        dev = model["deviation"]
        if dev:
            rows = []
            for direction in ("mesh_to_cad", "cad_to_mesh"):
                s = dev[direction]["stats"]
                rows.append(
                    {
                        "direction": direction,
                        "RMS mm": s["rms_mm"],
                        "mean mm": s["mean_mm"],
                        **{f"|d| {k} mm": v for k, v in s["abs_percentiles_mm"].items()},
                        "max out mm": s["max_outside_mm"],
                        "max in mm": s["max_inside_mm"],
                        "refined": dev[direction]["refined_share"],
                    }
                )
            parts.append("<h3>Deviation (positive = mesh outside the CAD model)</h3>")
            parts.append(_table(rows, list(rows[0].keys())))
            parts.append(f"<p>Distances not refined on the exact surface are within "
                         f"{dev['unrefined_bound_mm']:.3g} mm (tessellation chord error).</p>")
            regions = dev["mesh_to_cad"]["regions"]
            if regions:
                rrows = [{"region": r, "RMS mm": v["stats"]["rms_mm"], "max out mm": v["stats"]["max_outside_mm"],
                          "max in mm": v["stats"]["max_inside_mm"], "area mm2": v["stats"]["area_mm2"]}
                         for r, v in regions.items()]
                parts.append(_table(rrows, list(rrows[0].keys())))
        cont = model["continuity"]
        if cont:
            s = cont["summary"]
            parts.append("<h3>Continuity across seams</h3>")
            parts.append(_table([{"edges": s["edges"], **s["class_counts"], "worst": s["worst_class"],
                                  "max gap mm": s["max_gap_mm"], "max angle deg": s["max_angle_deg"],
                                  "max curvature jump": s["max_curvature_jump"]}],
                                ["edges", "gap", "C0", "G1", "G2", "worst", "max gap mm", "max angle deg",
                                 "max curvature jump"]))
        if model["knots"]:
            krows = [{"face": k["face"], "kind": k["kind"], "degree": k["degree"],
                      "C^k inside (u, v)": k["min_continuity"]} for k in model["knots"]]
            parts.append("<h3>Continuity inside faces (knots)</h3>")
            parts.append(_table(krows, list(krows[0].keys())))
        for fig_name, path in figures.get(name, {}).items():
            data = base64.b64encode(Path(path).read_bytes()).decode("ascii")
            parts.append(f"<h3>{html.escape(fig_name)}</h3><img alt='{html.escape(fig_name)}' "
                         f"src='data:image/png;base64,{data}'>")
    parts.append("<h2>Timings</h2>")
    parts.append(_table([{"stage": k, "seconds": v} for k, v in report["timings_s"].items()], ["stage", "seconds"]))
    parts.append("</body></html>")
    return "\n".join(parts)


@dataclass(frozen=True)
class ReportDocument:
    """What the report holds: the input summary (file, bodies, side), the frame (``as_dict``), one
    ``ModelReport`` per model, the run's stage timings (s)."""

    input_summary: dict[str, Any]
    frame: dict[str, Any]
    models: tuple[ModelReport, ...]
    timings_s: dict[str, float]

    def build(self) -> dict[str, Any]:
        for m in self.models:
            for fig_name, path in m.figures.items():
                if not Path(path).is_file():
                    raise FileNotFoundError(f"figure '{fig_name}' of model '{m.name}' is missing: {path}")
        return build_report(input_summary=self.input_summary, frame=self.frame, models=list(self.models),
                            timings_s=self.timings_s)


@exporter("report", "json")
def report_json(doc: ReportDocument, out_dir: Path) -> Path:
    """report.json (schema above); figures referred to by file name (they are expected beside it)."""
    path = out_dir / "report.json"
    with staged_file(path) as tmp:
        tmp.write_text(json.dumps(doc.build(), indent=1, allow_nan=False) + "\n")
    return path


@exporter("report", "html")
def report_html(doc: ReportDocument, out_dir: Path) -> Path:
    """report.html: the same, with every figure embedded."""
    path = out_dir / "report.html"
    with staged_file(path) as tmp:
        tmp.write_text(render_html(doc.build(), {m.name: m.figures for m in doc.models}))
    return path
