"""Benchmark of the analysis stage: signed distances for ``[analysis] sample_points`` points (target < 2 s).

Shape: a NURBS sphere of radius 40 mm (a tibia's condyle scale) converted to a
native B-spline face; points: area-weighted samples of its coarse tessellation
with a radial wave of +-0.3 mm, as a bone mesh would sit about a fitted model.
Prints tessellation time, distance time for ``[analysis] sample_points`` points
(exact projection included), the refined share and the worst error against the
closed-form distance |p| - R. Also times a whole ``shape_deviation`` (both
directions) and a continuity pass.

Then the analysis stage as ``reconstruct`` runs it, in one process (``analyse_shape``
below: tessellation, deviation both ways, continuity, three PNGs) on the phantom
tibia's NURBS model (target < 5 s) and on a shell of its
Bezier patches, about 3.5k Geom_BezierSurface faces sewn like a T-spline model
(target < 7 s): best of 3 wall-clock and process time, and the load average
(the 2 cores are shared: a loaded machine stretches wall time).

Run: .venv/bin/python benchmarks/bench_analysis.py
"""
from __future__ import annotations

import os
import time
from dataclasses import replace

import numpy as np
from OCP.BRepBuilderAPI import BRepBuilderAPI_NurbsConvert
from OCP.BRepPrimAPI import BRepPrimAPI_MakeSphere

from bonecad.analysis.continuity import seam_continuity
from bonecad.analysis.deviation import sample_surface, shape_deviation, signed_distance_to_shape
from bonecad.analysis.model import continuity_tolerances, tessellation_settings
from bonecad.analysis.statistics import settings_band_edges
from bonecad.mesh.closest import TriangleLocator
from bonecad.occ.tessellate import tessellate
from bonecad.settings import Settings

#: the shipped settings; their [analysis] tessellation tolerances and histogram bands (mm)
SETTINGS = Settings.load()
TESSELLATION = tessellation_settings(SETTINGS.analysis)
BANDS_MM = settings_band_edges(SETTINGS.analysis)

RADIUS = 40.0


def main() -> None:
    count = SETTINGS.analysis.sample_points
    shape = BRepBuilderAPI_NurbsConvert(BRepPrimAPI_MakeSphere(RADIUS).Shape(), True).Shape()
    t0 = time.perf_counter()
    tess = tessellate(shape, TESSELLATION)
    t_tess = time.perf_counter() - t0
    print(f"tessellation: {len(tess.triangles)} triangles, {t_tess:.2f} s, "
          f"chord error {tess.chord_error_mm.max():.4f} mm")

    coarse = tessellate(shape, replace(TESSELLATION, deflection_mm=0.1, max_edge_mm=2.0))
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
    exact = np.linalg.norm(samples.points, axis=1) - RADIUS
    err = np.abs(sd.distance_mm - exact)
    print(f"locator build: {t_loc:.2f} s")
    print(f"signed distance, {count} points: {best:.2f} s (best of 3; target < 2 s)")
    print(f"  refined on the exact surface: {100 * sd.refined.mean():.3f} %")
    print(f"  max error refined: {err[sd.refined].max():.2e} mm; max error all: {err.max():.2e} mm "
          f"(bound for unrefined: {tess.chord_error_mm.max():.4f} mm)")

    t0 = time.perf_counter()
    result = shape_deviation(mesh_v, coarse.triangles, tess, edges_mm=BANDS_MM, sample_points=count)
    print(f"shape_deviation both ways, {count} points each: {time.perf_counter() - t0:.2f} s "
          f"{ {k: round(v, 2) for k, v in result.timings_s.items()} }")
    s = result.mesh_to_cad.stats
    print(f"  mesh->CAD RMS {s.rms_mm:.4f} mm, p99 |d| {s.abs_percentiles_mm[3]:.4f} mm, "
          f"max out {s.max_outside_mm:.4f}, max in {s.max_inside_mm:.4f}")

    t0 = time.perf_counter()
    seam_continuity(BRepPrimAPI_MakeSphere(RADIUS).Shape(), tolerances=continuity_tolerances(SETTINGS.analysis))
    print(f"seam continuity (sphere): {time.perf_counter() - t0:.3f} s")


def bezier_shell(shape):
    """The B-spline faces of ``shape`` split into their Bezier patches and sewn into one shell."""
    from OCP.BRep import BRep_Tool
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace, BRepBuilderAPI_Sewing
    from OCP.GeomConvert import GeomConvert_BSplineSurfaceToBezierSurface
    from OCP.TColGeom import TColGeom_Array2OfBezierSurface

    from bonecad.occ.brep import faces

    sewing = BRepBuilderAPI_Sewing(1e-4)
    for face in faces(shape):
        split = GeomConvert_BSplineSurfaceToBezierSurface(BRep_Tool.Surface_s(face))
        patches = TColGeom_Array2OfBezierSurface(1, split.NbUPatches(), 1, split.NbVPatches())
        split.Patches(patches)
        for i in range(1, split.NbUPatches() + 1):
            for j in range(1, split.NbVPatches() + 1):
                sewing.Add(BRepBuilderAPI_MakeFace(patches.Value(i, j), 1e-7).Face())
    sewing.Perform()
    return sewing.SewedShape()


def analyse_shape(name: str, shape, bone, frame, out_dir):
    """The analysis stage of ``reconstruct`` (``bonecad.run.pipeline.analyse``) on a bare shape, all in
    this process: tessellation, deviation both ways, the three PNGs, seam and knot continuity (no face
    names). Returns the deviation with the tessellation's time among its steps."""
    from bonecad.analysis.model import model_continuity, model_deviation, tessellate_model
    from bonecad.render.figures import deviation_map_png, histograms_png, zebra_png

    view_frame = frame.axes.T  # columns: lateral, anterior, proximal
    t0 = time.perf_counter()
    tess = tessellate_model(shape, SETTINGS.analysis)
    t_tess = time.perf_counter() - t0
    zebra_png(out_dir / f"{name}_zebra.png", tess, view_frame, title=f"{name}: zebra (reflection lines)")
    model_continuity(shape, tess, None, SETTINGS.analysis)
    deviation = model_deviation(tess, bone, frame, SETTINGS.analysis)
    deviation_map_png(out_dir / f"{name}_deviation.png", bone.vertices, bone.faces, deviation.vertex_deviation_mm,
                      view_frame, title=f"{name}: deviation of the mesh from the CAD model, mm")
    histograms_png(out_dir / f"{name}_histograms.png",
                   {name: {"whole bone": deviation.mesh_to_cad.histogram, **deviation.mesh_to_cad.region_histograms}},
                   title=f"{name}: share of surface per deviation band")
    return replace(deviation, timings_s={"tessellate": t_tess, **deviation.timings_s})


def bench_models() -> None:
    import tempfile
    from pathlib import Path

    import bonecad
    from bonecad.contours.curves import contour_curves
    from bonecad.nurbs_model.model import build_nurbs
    from bonecad.occ.brep import faces

    bone = bonecad.phantom_tibia(settings=SETTINGS)
    frame = bonecad.anatomical_frame(bone, SETTINGS)
    nurbs = build_nurbs(contour_curves(bone, frame, settings=SETTINGS.curves), settings=SETTINGS.nurbs).shape
    out = Path(tempfile.mkdtemp())
    for name, shape, target in (("nurbs", nurbs, 5.0), ("bezier", bezier_shell(nurbs), 7.0)):
        wall, cpu = np.inf, np.inf
        for _ in range(3):
            t0, c0 = time.perf_counter(), time.process_time()
            dev = analyse_shape(name, shape, bone, frame, out)
            wall, cpu = min(wall, time.perf_counter() - t0), min(cpu, time.process_time() - c0)
        print(f"analyse_model {name}: {len(faces(shape))} faces, mesh {len(bone.faces)} triangles: "
              f"{wall:.2f} s wall, {cpu:.2f} s process (best of 3; target < {target:g} s; "
              f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores)")
        print(f"  steps {({k: round(v, 2) for k, v in dev.timings_s.items()})}; "
              f"RMS {dev.mesh_to_cad.stats.rms_mm:.4f} mm, "
              f"refined {100 * dev.mesh_to_cad.refined.mean():.3f} % / {100 * dev.cad_to_mesh.refined.mean():.3f} %, "
              f"unrefined bound {dev.unrefined_bound_mm:.4f} mm")


if __name__ == "__main__":
    main()
    bench_models()
