"""Fairness and accuracy per model kind and input (issues 47 and 48; docs/guides/fairness.md).

Models: the NURBS baseline, the T-spline, and the tensor-product B-spline fitted to the same tolerance by
whole knot lines (``[tspline] compare_tensor_product``). Fairness: ``bonecad.analysis.fairness`` (RMS of
the gradient of mean curvature over the exact surfaces, 1/mm^2; the NURBS and T-spline solids' faces, the
tensor product's tube). Accuracy: the share of the mesh within 0.25 mm of the model and the RMS (mm) -- the
NURBS solid by ``shape_deviation`` (mesh -> CAD), the two fitted tubes at their fit points (apex holes out).

``--noise``: the noise stop (issue 48) on a clean tibia with normal noise of RMS a (mm) at wavelength L
(mm) (64 random plane waves, seeded): the T-spline's control points, its RMS distance from the clean truth
against the noisy mesh's own, its fairness, and why the fit stopped.

Run: python benchmarks/bench_fairness.py [STEM ...]            (stems of ../shared/data/tibia)
     python benchmarks/bench_fairness.py --noise [STEM]        (default LHDL_CT_tibia_no_fib_r)
"""
from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bonecad.analysis.deviation import shape_deviation  # noqa: E402
from bonecad.analysis.fairness import shape_fairness, surface_fairness  # noqa: E402
from bonecad.mesh.closest import TriangleLocator  # noqa: E402
from bonecad.nurbs_model.model import build_nurbs  # noqa: E402
from bonecad.occ.tessellate import tessellate  # noqa: E402
from bonecad.run.bones import bone_settings  # noqa: E402
from bonecad.run.pipeline import frame_and_contours, load_input  # noqa: E402
from bonecad.settings import Settings  # noqa: E402
from bonecad.splines.tspline.fit import initial_parameters  # noqa: E402
from bonecad.tspline_model.model import build_tspline_model, hole_masks  # noqa: E402
from bonecad.analysis.model import region_labels, tessellation_settings  # noqa: E402
from bonecad.analysis.statistics import settings_band_edges  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "tibia"
INPUTS = ("LHDL_CT_tibia_no_fib_r", "ICL_MRI_tibia_r")
NOISE = ((0.0, 3.0), (0.05, 1.0), (0.15, 3.0), (0.3, 5.0), (0.5, 10.0), (1.0, 10.0))


def noise_field(points: np.ndarray, rms_mm: float, wavelength_mm: float, seed: int = 0,
                modes: int = 64) -> np.ndarray:
    """(n,) mm: a random field of RMS ``rms_mm`` at one wavelength (a sum of plane waves in random directions)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(modes, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    f = np.cos(points @ (2 * np.pi / wavelength_mm * d).T + rng.uniform(0, 2 * np.pi, modes)).sum(axis=1)
    return f * rms_mm / np.sqrt(np.mean(f**2))


def largest_body(path: Path) -> trimesh.Trimesh:
    mesh = trimesh.load_mesh(path)
    return max(mesh.split(only_watertight=False), key=lambda b: abs(b.volume))


def prepared(mesh: trimesh.Trimesh, folder: Path, settings: Settings):
    path = folder / "input.stl"
    mesh.export(path)
    bone = load_input(path, settings)
    settings = bone_settings(bone, settings)
    frame, contours, _ = frame_and_contours(bone, settings)
    return bone, settings, frame, contours


def tube_accuracy(fit) -> str:
    return f"{fit.stats.share_within:.4f} / {fit.stats.rms_mm:.3f}"


def model_kinds(stem: str) -> None:
    settings = Settings.load().replace("tspline", compare_tensor_product=True)
    with tempfile.TemporaryDirectory() as folder:
        bone, settings, frame, contours = prepared(largest_body(DATA / f"{stem}.stl"), Path(folder), settings)
    step = settings.analysis.fairness_step_mm
    start = time.process_time()
    nurbs = build_nurbs(contours, settings=settings.nurbs)
    dev = shape_deviation(bone.vertices, bone.faces, tessellate(nurbs.shape, tessellation_settings(settings.analysis)),
                          sample_points=100_000, edges_mm=settings_band_edges(settings.analysis))
    labels = region_labels(frame)
    rows = [("NURBS", nurbs.summary()["control_points"], shape_fairness(nurbs.shape, step_mm=step, labels=labels),
             f"{dev.mesh_to_cad.share_within(0.25):.4f} / {dev.mesh_to_cad.stats.rms_mm:.3f} (solid)")]
    model = build_tspline_model(bone, frame, contours, settings=settings.tspline,
                                apex_hole_radius_mm=settings.curves.apex_hole_radius_mm)
    rows.append(("T-spline (solid)", model.control_points,
                 shape_fairness(model.shape, step_mm=step, labels=labels), f"{tube_accuracy(model.fit)} (fit points)"))
    rows.append(("T-spline (tube)", model.control_points,
                 surface_fairness([model.tspline], step_mm=step),
                 f"{tube_accuracy(model.fit)} (fit points)"))
    tp = model.tensor_product_fit
    if tp is not None:
        rows.append(("tensor product (tube)", tp.tspline.n_control,
                     surface_fairness([tp.tspline], step_mm=step),
                     f"{tube_accuracy(tp)} (fit points)"))
    print(f"\n{stem} ({time.process_time() - start:.0f} s CPU, loaded machine)")
    print(f"  {'model':24s} {'control pts':>11s}  fairness 1/mm^2: RMS, median, regions (RMS)   "
          "share within 0.25 mm / RMS mm")
    for name, cp, fair, acc in rows:
        regions = " ".join(f"{k} {v:.4f}" for k, v in fair.regions.items())
        print(f"  {name:24s} {cp:11d}  {fair.curvature_variation:.5f} {fair.typical:.5f} {regions}  {acc}")


def noise_stop(stem: str) -> None:
    clean = largest_body(DATA / f"{stem}.stl")
    samples, _ = trimesh.sample.sample_surface(clean, 40_000, seed=3)
    print(f"\n{stem} + normal noise: T-spline control points, RMS from the clean truth (model / noisy mesh, mm), "
          "fairness (1/mm^2), noise level, stop")
    for rms, wavelength in NOISE:
        moved = clean.vertices + clean.vertex_normals * noise_field(clean.vertices, rms, wavelength)[:, None]
        noisy = trimesh.Trimesh(moved, clean.faces, process=False)
        with tempfile.TemporaryDirectory() as folder:
            bone, settings, frame, contours = prepared(noisy, Path(folder), Settings.load())
        model = build_tspline_model(bone, frame, contours, settings=settings.tspline,
                                    apex_hole_radius_mm=settings.curves.apex_hole_radius_mm)
        holes = hole_masks(frame.to_bone(samples), frame, settings.curves.apex_hole_radius_mm)
        inside = samples[~np.logical_or(*holes)]
        d_model = initial_parameters(model.tspline, frame.to_bone(inside))[2]
        d_mesh = TriangleLocator(noisy.vertices, noisy.faces).query(inside).distance
        fair = shape_fairness(model.shape, step_mm=settings.analysis.fairness_step_mm)
        print(f"  a {rms:4.2f} L {wavelength:4.1f}: {model.control_points:6d} cp, "
              f"RMS {np.sqrt(np.mean(d_model**2)):.3f} / {np.sqrt(np.mean(d_mesh**2)):.3f}, "
              f"fairness {fair.curvature_variation:.5f} (median {fair.typical:.5f}), level {model.noise_level_mm:.3f}: "
              f"{model.fit.stopped[:60]}", flush=True)


if __name__ == "__main__":
    args = sys.argv[1:]
    if args[:1] == ["--noise"]:
        for name in args[1:] or ["LHDL_CT_tibia_no_fib_r"]:
            noise_stop(name)
    else:
        for name in args or INPUTS:
            model_kinds(name)
