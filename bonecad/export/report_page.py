"""report.html: the report.json content laid out for people, summary first.

Order: the summary (input, then one card per model with its verdict against the
run's tolerances), the 3-D view, the NURBS-versus-T-spline table, the figures
(the overlaid histograms, each model's deviation map and zebra, the curve plan;
each with a caption saying what it shows), the contour curves, the anatomical
frame, each model's details (deviation, regions, seam classes per face pair,
knots, the model's own figures), the timings. Every table cell holds one number or one short text: nested values are
laid out as their own rows or columns (:func:`cell` refuses a list or a dict).
"""
from __future__ import annotations

import base64
import html
from pathlib import Path
from typing import Any

from bonecad.settings import load_profile

#: names of unit vectors in the frame (the rest of its triples are points, scanner mm)
_DIRECTIONS = {"lateral", "anterior", "proximal", "direction", "normal", "major_direction"}
#: the deviation's two directions, as the page names them
_DIRECTION = {"mesh_to_cad": "mesh → CAD", "cad_to_mesh": "CAD → mesh"}
#: CSS class of each verdict's badge
_VERDICT_CLASS = {"met": "met", "not met": "missed", "stopped at the data's noise": "noise",
                  "not measured": "missed"}
_STYLE = """
body{font-family:system-ui,sans-serif;margin:1.5em 2em;color:#222;max-width:1500px}
h1{margin-bottom:0.2em}h2{border-bottom:2px solid #ddd;padding-bottom:0.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:0.6em 0}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}
th{background:#f0f0f0}td:first-child,th:first-child{text-align:left}
.cards{display:flex;flex-wrap:wrap;gap:1em;align-items:flex-start}.card{border:1px solid #bbb;border-radius:6px;
padding:0.8em 1em;background:#fafafa;flex:1 1 400px;max-width:620px}.card h3{margin:0 0 0.4em 0}
.card table{display:inline-table;vertical-align:top;margin:0.3em 0.8em 0.3em 0}
.verdict{display:inline-block;padding:2px 10px;border-radius:10px;font-weight:bold;color:#fff}
.met{background:#2e7d32}.missed{background:#c62828}.noise{background:#ef6c00}
.reason{font-size:0.9em;color:#444;max-width:42em}
img{max-width:100%;border:1px solid #ddd}figure{margin:0.8em 0 1.6em 0}figcaption{max-width:60em;color:#333}
"""


def cell(value: Any) -> str:
    """One table cell's text: a number, yes/no, or escaped text; a list or dict is refused."""
    if isinstance(value, (list, tuple, dict)):
        raise TypeError(f"a table cell holds one value, not {type(value).__name__}: {value!r:.80}")
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.4g}"
    return html.escape(str(value))


def table(rows: list[dict[str, Any]], columns: list[str] | None = None) -> str:
    """An HTML table of ``rows`` (one dict per row; columns: the first row's keys by default)."""
    if not rows:
        return "<p>none</p>"
    columns = columns if columns is not None else list(rows[0])
    head = "".join(f"<th>{html.escape(c)}</th>" for c in columns)
    body = "".join("<tr>" + "".join(f"<td>{cell(r.get(c))}</td>" for c in columns) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def flatten(value: Any, prefix: str = "") -> dict[str, Any]:
    """Nested dicts as one level of "a / b" keys; a list of numbers summarised in words (count, range)."""
    if isinstance(value, dict):
        out: dict[str, Any] = {}
        for k, v in value.items():
            out.update(flatten(v, f"{prefix} / {k}" if prefix else str(k)))
        return out
    if isinstance(value, (list, tuple)):
        return {prefix: _summarise_list(value)}
    return {prefix: value}


def _summarise_list(values: list | tuple) -> str:
    if not values:
        return "none"
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
        if len(values) <= 3:
            return " × ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in values)
        return f"{len(values)} values, {min(values):.4g} to {max(values):.4g}"
    if all(isinstance(v, (str, bool)) for v in values) and len(values) <= 3:
        return ", ".join(cell(v) for v in values)
    return f"{len(values)} entries"


def records(items: list[dict[str, Any]]) -> str:
    """A list of dicts as one table: a row per item, a column per (flattened) key."""
    rows = [flatten(item) for item in items]
    columns: list[str] = []
    for r in rows:
        columns += [k for k in r if k not in columns]
    return table(rows, columns)


def info_tables(info: dict[str, Any]) -> str:
    """A model's own figures: scalars (and nested dicts) as one key/value table, each list of
    dicts (surfaces, fit rounds, refits) as its own table."""
    scalars: dict[str, Any] = {}
    lists = []
    for key, value in info.items():
        if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            lists.append((key, value))
        else:
            scalars.update(flatten(value, key))
    parts = [table([{"quantity": k.replace("_", " "), "value": v} for k, v in scalars.items()])]
    for key, items in lists:
        parts.append(f"<h4>{html.escape(key.replace('_', ' '))}</h4>{records(items)}")
    return "".join(parts)


def _triple_unit(path: str) -> str:
    return "unit vector" if path.split(" / ")[-1] in _DIRECTIONS else "mm (input coordinates)"


def frame_rows(frame: dict[str, Any]) -> list[dict[str, Any]]:
    """The frame's entities, one row each: a point or direction as x, y, z; a scalar or pair as value."""
    rows = []
    for path, value in _leaves(frame):
        name = path.replace("_", " ")
        if isinstance(value, (list, tuple)) and len(value) == 3:
            rows.append({"entity": name, "x": value[0], "y": value[1], "z": value[2], "unit": _triple_unit(path)})
        elif isinstance(value, (list, tuple)):
            joined = " to " if path.startswith("regions") else " × "
            rows.append({"entity": name, "value": joined.join(f"{v:.4g}" for v in value), "unit": "mm"})
        else:
            unit = "mm" if path.endswith("_mm") or path.endswith("length") else ""
            rows.append({"entity": name, "value": value, "unit": unit})
    return rows


def _leaves(value: Any, prefix: str = ""):
    """(path, value) of every scalar or list of scalars; a list of lists (a matrix) gives a row each."""
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _leaves(v, f"{prefix} / {k}" if prefix else str(k))
    elif isinstance(value, (list, tuple)) and any(isinstance(v, (list, tuple, dict)) for v in value):
        for i, v in enumerate(value):
            yield from _leaves(v, f"{prefix} / {i + 1}")
    else:
        yield prefix, value


def _input_section(summary: dict[str, Any]) -> str:
    bodies = summary.get("bodies") or []
    rows = [{"quantity": k.replace("_", " "), "value": v} for k, v in summary.items()
            if k not in ("bodies", "repairs") and not isinstance(v, (list, dict))]
    kept = [{"body": b.get("role"), "kept": i == 0, "triangles": b.get("triangles"),  # the intake's first body
             "volume cm3": None if b.get("volume_mm3") is None else b["volume_mm3"] / 1000,
             "length mm": b.get("length_mm")} for i, b in enumerate(bodies)]
    repairs = summary.get("repairs") or []
    parts = ["<div class='card'><h3>Input</h3>", table(rows)]
    if kept:
        parts += [f"<h4>Bodies ({sum(k['kept'] for k in kept)} kept, {sum(not k['kept'] for k in kept)} dropped)"
                  "</h4>", table(kept)]
    parts.append("<h4>Repairs</h4>" + ("<ul>" + "".join(f"<li>{html.escape(str(r))}</li>" for r in repairs)
                                         + "</ul>" if repairs else "<p>none</p>"))
    parts.append("</div>")
    return "".join(parts)


def _model_card(name: str, card: dict[str, Any]) -> str:
    verdict = card["verdict"]
    badge = f"<span class='verdict {_VERDICT_CLASS[verdict]}' data-verdict='{html.escape(verdict)}'>" \
            f"{html.escape(verdict)}</span>"
    within = [{"within": f"{k} mm", "share of surface": f"{100 * v:.2f} %"} for k, v in card["within_mm"].items()]
    both = [{"direction": _DIRECTION[d], "max mm": card["max_mm"][d],
             "RMS mm": card["rms_mm"][d]} for d in card["max_mm"]]
    seams = [{"class": k, "seams": v} for k, v in card["seam_classes"].items()]
    files = [{"file": k, "size kB": round(v / 1024, 1)} for k, v in card["files_bytes"].items()]
    checks = [{"check": c["check"], "measured": c["measured"], "target": c["target"], "met": c["met"]}
              for c in card["checks"]]
    return "".join([
        f"<div class='card' id='card-{html.escape(name)}'><h3>{html.escape(name)} {badge}</h3>",
        f"<p class='reason'>{html.escape(card['reason'])}</p>",
        table([{"faces": card["faces"], "control points (caps included)": card["control_points"]}]),
        table(checks) if checks else "", table(within) if within else "", table(both) if both else "",
        table(seams) if seams else "", _fairness_table(card.get("fairness")), table(files) if files else "",
        "</div>"])


def _fairness_table(fairness: dict[str, Any] | None) -> str:
    """The card's fairness row: the RMS of the gradient of mean curvature, overall and per region."""
    if not fairness:
        return ""
    return table([{"fairness: curvature variation, 1/mm^2 (lower is fairer)": fairness["curvature_variation_per_mm2"],
                   **{f"{k}": v for k, v in fairness["regions"].items()},
                   "median over the surface": fairness.get("typical_per_mm2")}])


def _deviation_tables(dev: dict[str, Any]) -> str:
    rows = []
    for direction in ("mesh_to_cad", "cad_to_mesh"):
        s = dev[direction]["stats"]
        rows.append({"direction": _DIRECTION[direction], "RMS mm": s["rms_mm"], "mean mm": s["mean_mm"],
                     **{f"|d| {k} mm": v for k, v in s["abs_percentiles_mm"].items()},
                     "max out mm": s["max_outside_mm"], "max in mm": s["max_inside_mm"],
                     "refined share": dev[direction]["refined_share"]})
    parts = ["<h3>Deviation (positive = mesh outside the CAD model)</h3>", table(rows),
             f"<p>Distances not refined on the exact surface are within {dev['unrefined_bound_mm']:.3g} mm "
             "(tessellation chord error).</p>"]
    regions = dev["mesh_to_cad"]["regions"]
    if regions:
        parts.append(table([{"region": r, "RMS mm": v["stats"]["rms_mm"], "max out mm": v["stats"]["max_outside_mm"],
                             "max in mm": v["stats"]["max_inside_mm"], "area mm2": v["stats"]["area_mm2"]}
                            for r, v in regions.items()]))
    return "".join(parts)


def _continuity_tables(cont: dict[str, Any]) -> str:
    s = cont["summary"]
    parts = ["<h3>Continuity across seams</h3>",
             table([{"edges": s["edges"], **s["class_counts"], "worst": s["worst_class"], "max gap mm": s["max_gap_mm"],
                     "max angle deg": s["max_angle_deg"], "max curvature jump": s["max_curvature_jump"]}])]
    pairs = s.get("class_counts_by_face_pair") or {}
    if pairs:
        parts += ["<h4>Seam classes per face pair</h4>",
                  table([{"face pair": k.replace("|", " – "), **v} for k, v in pairs.items()])]
    return "".join(parts)


#: what each figure shows (by its name; ``{model}`` and ``{tolerance}`` filled in), in the page's order
CAPTIONS = {
    "histograms": "Share of the surface per 0.1 mm band of signed deviation (mesh → CAD; + = mesh outside the "
                  "model), the models overlaid, for the whole bone and each region, on a linear scale (the peak) "
                  "above a logarithmic one (the tails); dashed: the run's ±{tolerance} mm tolerance. A taller, "
                  "narrower peak at 0 is a closer fit; the outermost bands collect everything beyond the axis.",
    "deviation": "{model}: the input mesh coloured by its signed distance to the {model} model (red: mesh "
                 "outside the model, blue: inside; colour bar in mm), seen from the front, back, medial and "
                 "lateral sides.",
    "zebra": "{model}: reflection lines (zebra) on the model from the same four sides. Stripes that break or "
             "jump mark a seam that is not tangent-continuous (G1), kinks a curvature (G2) break; continuous "
             "smooth stripes mean a smooth surface. Where the stripes get denser than the pixels they fade to "
             "grey.",
    "curves": "Curve plan: the contour curves the models are built from, on the input mesh from the front and "
              "the lateral side (hidden parts faint), coloured by region; dashed: the region boundaries (mm "
              "above the {origin}).",
}


def figures_section(figures: dict[str, dict[str, Path]], tolerance_mm: float | None, origin: str) -> str:
    """Every figure (``figures``: model, "" for the run's own, -> name -> PNG), grouped by kind in the
    order of :data:`CAPTIONS` (other names after them), each with its caption; ``origin``: the frame's
    origin (the bone profile's), which heights are above."""
    order = {name: i for i, name in enumerate(CAPTIONS)}
    items = sorted(((order.get(name, len(order)), model, name, path) for model, named in figures.items()
                    for name, path in named.items()), key=lambda item: item[0])
    parts = []
    for _, model, name, path in items:
        template = CAPTIONS.get(name, "{model}: " + name if model else name)
        tolerance = "-" if tolerance_mm is None else f"{tolerance_mm:g}"
        parts.append(_figure(template.format(model=model, tolerance=tolerance, origin=origin), path))
    return "".join(parts)


def _figure(caption: str, path: Path) -> str:
    data = base64.b64encode(Path(path).read_bytes()).decode("ascii")
    return (f"<figure><img alt='{html.escape(caption)}' src='data:image/png;base64,{data}'>"
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def render_html(report: dict[str, Any], figures: dict[str, dict[str, Path]], viewer: str = "") -> str:
    """report.html text from the report.json content; ``figures`` maps model ("" for the run's own) ->
    figure name -> PNG path (embedded); ``viewer``: the 3-D view's HTML (empty: none)."""
    parts = ["<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>bonecad report</title>",
             f"<style>{_STYLE}</style></head><body>", "<h1>bonecad report</h1>", "<h2 id='summary'>Summary</h2>"]
    tol = report.get("tolerances")
    if tol:
        parts.append(f"<p>Tolerances of this run ([tspline]): at least {100 * tol['share']:g} % of the surface within "
                     f"{tol['within_mm']:g} mm, no point beyond {tol['max_deviation_mm']:g} mm, RMS at most "
                     f"{tol['rms_mm']:g} mm; measured both ways (from the mesh to each model and from each model "
                     "to the mesh), and no model may fold.</p>")
    parts.append("<div class='cards'>" + _input_section(report["input"]))
    parts += [_model_card(name, card) for name, card in report.get("summary", {}).items()]
    parts.append("</div>")
    if viewer:
        parts += ["<h2 id='view'>3-D view</h2>", viewer]
    if report.get("comparison"):
        parts += ["<h2>NURBS versus T-spline</h2>", table(report["comparison"], ["quantity", "nurbs", "tspline"])]
    if any(figures.values()):
        origin = load_profile(report.get("frame", {}).get("bone", "tibia")).origin  # a tibia's frame.json names no bone
        parts += ["<h2 id='figures'>Figures</h2>", figures_section(figures, tol["within_mm"] if tol else None, origin)]
    if report.get("contours"):
        parts += ["<h2>Contour curves</h2>",
                  table([{"region": r["region"], "curves": r["curves"], "control points per curve":
                          r["control_points_per_curve"], "tolerance mm": r["tolerance_mm"],
                          "worst max deviation mm": r["worst_max_deviation_mm"],
                          "mean RMS mm": r["mean_rms_deviation_mm"],
                          "within tolerance": f"{r['within_tolerance']} of {r['curves']}", "repairs": r["repairs"]}
                         for r in report["contours"]])]
    if report.get("frame"):
        parts += ["<h2>Anatomical frame</h2>", table(frame_rows(report["frame"]),
                                                     ["entity", "x", "y", "z", "value", "unit"])]
    if report.get("morphometry"):
        parts += ["<h2>Morphometry (bonecad measure)</h2>",
                  table([{"parameter": k, "value": round(v, 1)} for k, v in report["morphometry"].items()],
                        ["parameter", "value"])]
    for name, model in report["models"].items():
        parts.append(f"<h2>Model: {html.escape(name)}</h2>")
        if model["deviation"]:
            parts.append(_deviation_tables(model["deviation"]))
        if model["continuity"]:
            parts.append(_continuity_tables(model["continuity"]))
        if model["knots"]:
            parts += ["<h3>Continuity inside faces (knots)</h3>",
                      records([{"face": k["face"], "kind": k["kind"], "degree": k["degree"],
                                "C^k inside (u, v)": k["min_continuity"]} for k in model["knots"]])]
        if model["info"]:
            parts += ["<h3>Model figures</h3>", info_tables(model["info"])]
    parts += ["<h2>Timings</h2>", table([{"stage": k, "seconds": v} for k, v in report["timings_s"].items()]),
              "</body></html>"]
    return "\n".join(parts)
