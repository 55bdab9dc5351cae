"""Cohort folders, shape models and morphs (issue 21): ``bonecad shape-model build`` and ``bonecad morph``.

A cohort folder (what ``bonecad cohort`` writes, and ``write_cohort`` from a list of meshes):

- ``cohort.csv``: a ``bone`` column, one column per named parameter (mm, degrees), and columns
  prefixed ``fit_`` (the template fit's figures; not parameters); a bone whose template fit
  failed has no points file and is left out;
- ``points/<bone>.npy``: the bone's (n, 3) template control points (bone coordinates, mm);
- ``surface/<bone>.npz`` (optional): ``points`` (m, 3) and ``weights`` (m,) of its mesh surface in
  bone coordinates (``template.surface_targets``): the leave-one-out generalisation is measured to it.

A shape model is saved as ``shape_model.npz`` with the JSON sidecar ``shape_model.json``
(version, bones, parameter names and ranges, alignment, compactness, figures).
"""
from __future__ import annotations

import csv
import json
import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from bonecad.analysis.shape_model import (ShapeModel, baselines_mm, build_shape_model, generalisation_mm,
                                          grid_points, grid_triangles, held_surface, morph_weights, normal_offsets,
                                          predict_parameters,
                                          specificity_mm)
from bonecad.anatomy.frame import AnatomicalFrame, anatomical_frame
from bonecad.anatomy.morphometry import ankle_turn_deg, measure_tibia, tibial_tuberosity
from bonecad.contours.curves import contour_curves
from bonecad.errors import InputError
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.run.executor import executor_for
from bonecad.settings import Settings
from bonecad.staging import staged_output
from bonecad.tspline_model.template import TemplateFit, fit_template, surface_targets, template_shape, template_tspline

log = logging.getLogger(__name__)

MODEL_FILE, META_FILE = "shape_model.npz", "shape_model.json"
#: columns of a cohort table that are not shape parameters (``bonecad cohort``'s bookkeeping)
_NOT_PARAMETERS = frozenset({"bone", "id", "path", "status", "error", "side", "cpu_s", "wall_s", "worker"})
#: numbers of modes the generalisation is reported for
GENERALISATION_MODES = (1, 2, 3, 5, 10)


def template_fit_bone(bone: BoneMesh, settings: Settings, *, frame: AnatomicalFrame | None = None
                      ) -> tuple[TemplateFit, np.ndarray, np.ndarray]:
    """Frame (unless given), contour curves and template fit of one bone: (fit, surface points (m, 3), their
    weights).

    One BLAS thread: the curve fits' many small dense solves cost ~4x the CPU time with a thread pool
    (phantom: 4.1 s against 15.7 s on the shared 2-core machine)."""
    with threadpool_limits(limits=1, user_api="blas"):
        if frame is None:
            frame = anatomical_frame(bone, settings=settings.anatomy, plausible=settings.units)
        contours = contour_curves(bone, frame, settings=settings.curves)
        radius = settings.curves.apex_hole_radius_mm
        fit = fit_template(bone, frame, contours, settings.template, apex_hole_radius_mm=radius,
                           ankle_turn_deg=ankle_turn_deg(bone, frame, settings.morphometry),
                           tuberosity_height_mm=float(tibial_tuberosity(bone, frame, settings.morphometry)[2]))
        points, weights = surface_targets(bone, frame, settings.template, apex_hole_radius_mm=radius)
    return fit, points, weights


def save_surface(path: Path, surface: tuple[np.ndarray, np.ndarray]) -> None:
    """A bone's surface file ``surface/<bone>.npz``: ``points`` (m, 3) mm and area ``weights`` (m,) mm^2."""
    np.savez(path, points=surface[0], weights=surface[1])


def load_surface(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(points, weights) of a surface file (``save_surface``)."""
    with np.load(path) as data:
        return data["points"], data["weights"]


def fit_figures(fit: TemplateFit) -> dict[str, float]:
    """A template fit's figures as cohort table columns ("fit_" names: no shape parameters)."""
    return {"fit_share_within": fit.share_within, "fit_max_mm": fit.max_mm, "fit_rms_mm": fit.rms_mm,
            "fit_cpu_s": fit.cpu_s}


def _fit_bones(bones: Sequence[BoneMesh], settings: Settings) -> list[tuple[TemplateFit, np.ndarray, np.ndarray]]:
    return [template_fit_bone(bone, settings) for bone in bones]


def write_cohort(bones: Sequence[tuple[str, BoneMesh, Mapping[str, float]]], out_dir: str | Path,
                 settings: Settings, *, background: bool = False) -> dict[str, TemplateFit]:
    """A cohort folder (module docstring) from (name, mesh, parameters) triples; ``background``: the second
    half of the bones fitted in a forked child on the second core (``executor_for``), the same fits."""
    fits = {}
    half = len(bones) // 2
    with executor_for(background) as ex:
        job = ex.submit(_fit_bones, [bone for _, bone, _ in bones[half:]], settings)
        fitted = _fit_bones([bone for _, bone, _ in bones[:half]], settings) + job.result()
    with staged_output(out_dir) as tmp:
        (tmp / "points").mkdir()
        (tmp / "surface").mkdir()
        rows = []
        for (name, _, params), (fit, points, weights) in zip(bones, fitted):
            fits[name] = fit
            np.save(tmp / "points" / f"{name}.npy", fit.control_points)
            save_surface(tmp / "surface" / f"{name}.npz", (points, weights))
            rows.append({"bone": name, **{k: float(v) for k, v in params.items()}, **fit_figures(fit)})
            log.info("%s: template fit %s", name, fit.summary())
        with open(tmp / "cohort.csv", "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    return fits


def read_cohort(cohort: str | Path) -> tuple[list[str], np.ndarray, dict[str, np.ndarray]]:
    """(bones, (m, n, 3) control points, parameter name -> (m,) values) of a cohort folder; bones without a
    points file (failed fits) are left out, and so are non-numeric columns."""
    cohort = Path(cohort)
    table = cohort / "cohort.csv"
    try:
        with open(table, newline="") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise InputError(f"cannot read the cohort table: {exc.strerror}", table) from None
    key = "bone" if rows and "bone" in rows[0] else "id"  # ``bonecad cohort`` names its bones "id"
    if not rows or key not in rows[0]:
        raise InputError("the cohort table needs a 'bone' (or 'id') column and at least one row", table)
    rows = [r for r in rows if r.get("status", "done") == "done" and (cohort / "points" / f"{r[key]}.npy").is_file()]
    if len(rows) < 3:
        raise InputError(f"fewer than 3 bones with template control points in {cohort / 'points'}", table)
    names = [k for k in rows[0] if k not in _NOT_PARAMETERS and not k.startswith("fit_")]
    params = {}
    for k in names:
        try:
            params[k] = np.array([float(r[k]) if r[k] not in ("", None) else math.nan for r in rows])
        except ValueError:
            continue  # a text column (a path, a note) is no parameter
    shapes = [np.load(cohort / "points" / f"{r[key]}.npy") for r in rows]
    if len({s.shape for s in shapes}) != 1:
        raise InputError("the bones' control-point arrays differ in shape (fitted with different templates?)",
                         cohort / "points")
    return [r[key] for r in rows], np.stack(shapes), params


def build_model_folder(out_dir: str | Path, cohort: str | Path, settings: Settings, *,
                       figures: bool = True) -> dict:
    """``bonecad shape-model build``: the model, its figures (compactness, leave-one-out generalisation with
    the two baselines when the cohort has surfaces, specificity) and the mode pictures, into ``out_dir``."""
    with threadpool_limits(limits=1, user_api="blas"):
        return _build_model_folder(out_dir, cohort, settings, figures=figures)


def _build_model_folder(out_dir: str | Path, cohort: str | Path, settings: Settings, *, figures: bool) -> dict:
    bones, shapes, params = read_cohort(cohort)
    sm, tpl = settings.shape_model, settings.template
    model = build_shape_model(shapes, bones, params, sm)
    arrays, meta = model.to_arrays()
    figures_out: dict = {"bones": len(bones)}
    surfaces = [Path(cohort) / "surface" / f"{b}.npz" for b in bones]
    if all(p.is_file() for p in surfaces):
        held = []
        for p, cp in zip(surfaces, shapes):
            held.append(held_surface(cp, tpl, *load_surface(p), samples=sm.surface_samples, seed=sm.seed))
        modes = [k for k in GENERALISATION_MODES if k <= len(bones) - 2] or [1]
        gen = generalisation_mm(shapes, held, modes, sm, tpl)
        figures_out["generalisation_rms_mm"] = {str(k): _stats(gen[:, c]) for c, k in enumerate(modes)}
        length = params.get("length_mm")
        if length is not None and np.all(np.isfinite(length)):
            base = baselines_mm(shapes, length, held, tpl)
            figures_out["baseline_mean_shape_rms_mm"] = _stats(base[:, 0])
            figures_out["baseline_scaled_mean_rms_mm"] = _stats(base[:, 1])
        figures_out["per_bone"] = {b: [round(float(x), 4) for x in gen[i]] for i, b in enumerate(bones)}
    else:
        figures_out["generalisation_rms_mm"] = "not measured: the cohort has no surface/<bone>.npz files"
    spec = specificity_mm(model, shapes, 5, sm, tpl)
    figures_out["specificity_5_modes_rms_mm"] = _stats(spec)
    meta["figures"] = figures_out
    with staged_output(out_dir) as tmp:
        np.savez(tmp / MODEL_FILE, **arrays)  # type: ignore[arg-type]
        (tmp / META_FILE).write_text(json.dumps(meta, indent=2))
        if figures:
            modes_png(model, tpl, tmp / "shape_modes.png")
    return meta


def _stats(values: np.ndarray) -> dict:
    """Over the bones: the RMS of their figures (each an RMS over a surface), the mean and the largest (mm)."""
    return {"rms": round(float(np.sqrt(np.mean(np.square(values)))), 4), "mean": round(float(np.mean(values)), 4),
            "max": round(float(np.max(values)), 4)}


def load_model(path: str | Path) -> ShapeModel:
    """A saved shape model: its folder, or its .npz (the .json sidecar beside it)."""
    path = Path(path)
    npz = path / MODEL_FILE if path.is_dir() else path
    meta_path = npz.with_suffix(".json")
    try:
        meta = json.loads(meta_path.read_text())
        with np.load(npz) as data:
            return ShapeModel.from_arrays(dict(data), meta)
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(f"cannot read the shape model: {exc}", npz) from None


def modes_png(model: ShapeModel, template, path: Path, *, modes: int = 3) -> Path:
    """The mean and each of the first ``modes`` modes at -3 and +3 SD, rendered (anterior view, coloured by
    the offset from the mean along its normal)."""
    from bonecad.render.figures import shape_modes_png

    tri = grid_triangles()
    mean = grid_points(model.mean, template)
    panels = [("mean shape", mean, tri, np.zeros(len(mean)))]
    offsets = []
    for k in range(min(modes, len(model.variances))):
        for sd in (-3.0, 3.0):
            w = np.zeros(k + 1)
            w[k] = sd * model.sd[k]
            pts = grid_points(model.shape(w), template)
            offsets.append(normal_offsets(mean, pts, tri))
            share = 100 * model.variances[k] / model.variances.sum()
            panels.append((f"mode {k + 1} ({share:.0f} %)\n{sd:+.0f} SD", pts, tri, offsets[-1]))
    # one scale for all: most of every surface (the ends' offsets along the axis would wash out the rest)
    limit = max(0.5, float(np.percentile(np.abs(np.concatenate(offsets)), 95))) if offsets else 1.0
    return shape_modes_png(path, panels, np.eye(3), title="Template shape model: mean and modes at -3 / +3 SD",
                           limit_mm=round(limit, 1))


def parse_parameter_flags(extra: Sequence[str], model: ShapeModel) -> dict[str, float]:
    """``--length 380 --plateau-width 78`` -> {"length_mm": 380, "plateau_width_mm": 78}: a flag names a
    model parameter with its unit suffix (_mm, _deg) dropped and - for _."""
    known = {n.removesuffix("_mm").removesuffix("_deg").replace("_", "-"): n for n in model.parameter_names}
    known.update({n.replace("_", "-"): n for n in model.parameter_names})
    out = {}
    items = list(extra)
    while items:
        flag = items.pop(0)
        if not flag.startswith("--") or flag[2:] not in known:
            flags = sorted({n.removesuffix("_mm").removesuffix("_deg").replace("_", "-")
                            for n in model.parameter_names})
            raise InputError(f"unknown option {flag!r}; the model's parameters: "
                             + ", ".join("--" + f for f in flags))
        if not items:
            raise InputError(f"option {flag} needs a value")
        value = items.pop(0)
        try:
            out[known[flag[2:]]] = float(value)
        except ValueError:
            raise InputError(f"option {flag}: expected a number, got {value!r}") from None
    return out


def measure_shape(shape, settings: Settings) -> dict[str, float]:
    """``bonecad measure`` of a closed solid (a morph; bone coordinates, mm): its tessellation (the analysis
    settings, welded) as the bone mesh, the anatomical frame and the measure. Not through the mesh intake:
    a solid is one closed body, and the intake's fused-bone rule (a neck near an end) has taken a morph's
    malleolus for a talus."""
    import trimesh

    from bonecad.analysis.model import tessellate_model

    tess = tessellate_model(shape, settings.analysis)
    welded = trimesh.Trimesh(tess.vertices, tess.triangles, process=True)
    bone = BoneMesh(np.asarray(welded.vertices), np.asarray(welded.faces), source="morph")
    frame = anatomical_frame(bone, settings=settings.anatomy, plausible=settings.units)
    return measure_tibia(bone, frame, settings.morphometry).values()


def run_morph(model_path: str | Path, out_dir: str | Path, settings: Settings, *,
              parameters: Mapping[str, float] | None = None, modes: Sequence[float] | None = None) -> dict:
    """``bonecad morph``: a tibia from named parameters (regression to mode weights) or from mode weights
    (in SD units): morph.step, morph.iges, morph.tsm, morph_points.npy and morph.json into ``out_dir``.

    morph.json holds the mode weights, the parameters predicted for the shape by the regression, and those
    measured back on the morph's solid by ``bonecad measure`` (its tessellation through the intake, the frame
    and the measure, as a mesh would go).
    """
    from bonecad.export.registry import export

    model = load_model(model_path)
    if (parameters is None) == (modes is None):
        raise InputError("give either parameters (e.g. --length 380) or --modes, not both or neither")
    if modes is not None:
        if len(modes) > len(model.variances):
            raise InputError(f"--modes: the model has {len(model.variances)} modes, got {len(modes)} weights")
        weights = np.asarray(modes, dtype=np.float64) * model.sd[: len(modes)]
    else:
        weights = morph_weights(model, dict(parameters or {}), settings.shape_model)
    points = model.shape(weights)
    shape = template_shape(template_tspline(points, settings.template), settings.template,
                           faces=settings.tspline)
    predicted = predict_parameters(model, weights, settings.shape_model)
    doc = {"model": str(model_path), "mode_weights_sd": np.round(weights / model.sd[: len(weights)], 4).tolist(),
           "given_parameters": dict(parameters or {}),
           "predicted_parameters": {k: round(v, 3) for k, v in predicted.items()},
           "measured_parameters": {k: round(v, 3) for k, v in measure_shape(shape.shape, settings).items()},
           "coordinates": "bone coordinates of the shape model (mm; x lateral, y anterior, z proximal)"}
    with staged_output(out_dir) as tmp:
        export("morph", shape, tmp)
        np.save(tmp / "morph_points.npy", points)
        (tmp / "morph.json").write_text(json.dumps(doc, indent=2))
    return doc
