"""Stress of the T-spline's conversion to a closed solid: the phantom's fitted tube refined at
random to over 10,000 control points, its control points moved, then capped, merged into B-spline
faces and sewn as the model does. Prints, per case, the size, the times (s) and the checks
(valid, closed, one shell, volume against the fitted model's).

Run: python benchmarks/bench_tspline_sewing.py [target control points ...]   (default 11000 20000)
"""
from __future__ import annotations

import sys
import time

import numpy as np
from OCP.TopAbs import TopAbs_SHELL
from OCP.TopExp import TopExp_Explorer

import bonecad
from bonecad.contours.curves import contour_curves
from bonecad.occ.brep import free_edge_count, is_valid, volume_mm3
from bonecad.settings import Settings
from bonecad.splines.tspline import TSpline, refine_elements
from bonecad.tspline_model.model import occ_shape, apex_caps, build_tspline_model, fit_points, hole_masks

#: largest share of the elements halved in a round, and the control points' random move (mm)
SPLIT_SHARE = 0.15
NOISE_MM = 0.3


def refined_at_random(tube: TSpline, target: int, rng: np.random.Generator) -> TSpline:
    """Halve random elements (in s, t or both) round after round until ``target`` control points."""
    while tube.n_control < target:
        n_e = tube.extraction.n_elements
        # a lone split adds ~10 control points (with the T-junctions' extensions): near the target, fewer
        count = max(1, min(int(SPLIT_SHARE * n_e), (target - tube.n_control) // 10))
        elements = rng.choice(n_e, count, replace=False)
        axes = rng.random((len(elements), 2)) < 0.6
        axes[~axes.any(axis=1), 0] = True
        tube = refine_elements(tube, elements, axes).tspline
    return tube.with_control_points(tube.control_points + rng.normal(0.0, NOISE_MM, tube.control_points.shape),
                                    tube.weights)


def shells(shape) -> int:
    explorer, n = TopExp_Explorer(shape, TopAbs_SHELL), 0
    while explorer.More():
        n += 1
        explorer.Next()
    return n


def main(targets: list[int]) -> None:
    settings = Settings.load()
    clock = time.perf_counter()
    bone = bonecad.phantom_tibia()
    frame = bonecad.anatomical_frame(bone)
    contours = contour_curves(bone, frame, settings=settings.curves)
    model = build_tspline_model(bone, frame, contours, settings=settings.tspline,
                                apex_hole_radius_mm=settings.curves.apex_hole_radius_mm)
    vertices, _ = fit_points(bone, frame, settings.tspline)
    distal, proximal = hole_masks(vertices, model.frame, settings.curves.apex_hole_radius_mm)
    reference = volume_mm3(model.shape)
    print(f"phantom model: {model.control_points} control points, {reference:.1f} mm3, "
          f"{time.perf_counter() - clock:.1f} s; each case's volume against it (the control points moved "
          f"{NOISE_MM} mm at random)")
    print(f"{'target':>7s} {'control':>8s} {'elements':>8s} {'faces':>6s} {'refine s':>8s} {'caps s':>7s} "
          f"{'solid s':>8s} {'valid':>5s} {'free':>5s} {'shells':>6s} {'volume mm3':>12s} {'rel. diff':>9s}")
    for seed, target in enumerate(targets):
        rng = np.random.default_rng(seed)
        clock = time.perf_counter()
        tube = refined_at_random(model.tspline, target, rng)
        t_refine = time.perf_counter() - clock
        clock = time.perf_counter()
        caps = apex_caps(tube, model.parameterisation, vertices[distal], vertices[proximal])
        t_caps = time.perf_counter() - clock
        clock = time.perf_counter()
        solid, names = occ_shape(tube, caps, model.parameterisation, model.frame, settings=settings.tspline)
        t_solid = time.perf_counter() - clock
        volume = volume_mm3(solid)
        print(f"{target:7d} {tube.n_control:8d} {tube.extraction.n_elements:8d} {len(names):6d} {t_refine:8.1f} "
              f"{t_caps:7.2f} {t_solid:8.1f} {str(is_valid(solid)):>5s} {free_edge_count(solid):5d} "
              f"{shells(solid):6d} {volume:12.1f} {volume / reference - 1:9.1e}")


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [11000, 20000])
