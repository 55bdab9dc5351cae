"""Benchmark of the analysis stage: signed distances for 200 k points (target < 2 s).

Shape: a NURBS sphere of radius 40 mm (a tibia's condyle scale) converted to a
native B-spline face; points: area-weighted samples of its coarse tessellation
with a radial wave of +-0.3 mm, as a bone mesh would sit about a fitted model.
Prints tessellation time, distance time for ``[analysis] sample_points`` points
(exact projection included), the refined share and the worst error against the
closed-form distance |p| - R. Also times a whole ``shape_deviation`` (both
directions) and a continuity pass.

Run: /work/venv/bin/python benchmarks/bench_analysis.py
"""
from __future__ import annotations

import time

import numpy as np
from OCP.BRepBuilderAPI import BRepBuilderAPI_NurbsConvert
from OCP.BRepPrimAPI import BRepPrimAPI_MakeSphere

from bonecad.analysis.closest import TriangleLocator
from bonecad.analysis.continuity import seam_continuity
from bonecad.analysis.deviation import sample_surface, shape_deviation, signed_distance_to_shape
from bonecad.analysis.tessellation import TessellationSettings, tessellate
from bonecad.config import load_config

RADIUS = 40.0


def main() -> None:
    count = int(load_config()["analysis"]["sample_points"])
    shape = BRepBuilderAPI_NurbsConvert(BRepPrimAPI_MakeSphere(RADIUS).Shape(), True).Shape()
    t0 = time.perf_counter()
    tess = tessellate(shape)
    t_tess = time.perf_counter() - t0
    print(f"tessellation: {len(tess.triangles)} triangles, {t_tess:.2f} s, chord error {tess.chord_error_mm.max():.4f} mm")

    coarse = tessellate(shape, TessellationSettings(deflection_mm=0.1, max_edge_mm=2.0))
    unit = coarse.vertices / RADIUS
    wave = 0.3 * np.sin(3 * np.arctan2(unit[:, 1], unit[:, 0])) * np.cos(2 * np.arcsin(np.clip(unit[:, 2], -1, 1)))
    mesh_v = coarse.vertices + unit * wave[:, None]
    samples = sample_surface(mesh_v, coarse.triangles, count, seed=0)

    t0 = time.perf_counter()
    locator = TriangleLocator(tess.vertices, tess.triangles)
    t_loc = time.perf_counter() - t0
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        sd = signed_distance_to_shape(samples.points, tess, locator=locator)
        best = min(best, time.perf_counter() - t0)
    t0 = time.perf_counter()
    signed_distance_to_shape(samples.points, tess, locator=locator, certify=True)
    t_cert = time.perf_counter() - t0
    exact = np.linalg.norm(samples.points, axis=1) - RADIUS
    err = np.abs(sd.distance_mm - exact)
    print(f"locator build: {t_loc:.2f} s")
    print(f"signed distance, {count} points: {best:.2f} s (best of 3; target < 2 s)")
    print(f"  with a certified first guess (default for shapes of several faces): {t_cert:.2f} s")
    print(f"  refined on the exact surface: {100 * sd.refined.mean():.3f} %")
    print(f"  max error refined: {err[sd.refined].max():.2e} mm; max error all: {err.max():.2e} mm "
          f"(bound for unrefined: {tess.chord_error_mm.max():.4f} mm)")

    t0 = time.perf_counter()
    result = shape_deviation(mesh_v, coarse.triangles, shape, sample_points=count, tessellation=tess)
    print(f"shape_deviation both ways, {count} points each: {time.perf_counter() - t0:.2f} s "
          f"{ {k: round(v, 2) for k, v in result.timings_s.items()} }")
    s = result.mesh_to_cad.stats
    print(f"  mesh->CAD RMS {s.rms_mm:.4f} mm, p99 |d| {s.abs_percentiles_mm[3]:.4f} mm, "
          f"max out {s.max_outside_mm:.4f}, max in {s.max_inside_mm:.4f}")

    t0 = time.perf_counter()
    seam_continuity(BRepPrimAPI_MakeSphere(RADIUS).Shape())
    print(f"seam continuity (sphere): {time.perf_counter() - t0:.3f} s")


if __name__ == "__main__":
    main()
