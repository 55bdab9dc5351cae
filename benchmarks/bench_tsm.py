"""Figures of the .tsm files of fitted models: the phantom and every mesh in ../shared/data/tibia.

Per model: the closed Fusion cage (faces, edges, vertices, T-junctions, star points, file size,
write and read time), whether it reads back exactly, the open Rhino patch's largest difference
from the T-spline at 10,000 points (and which clamped mesh held it), and the size of the region
where Fusion's star-point rules (unpublished) take over from bonecad's surface: the two apex
caps' area (share of the whole surface) and their largest distance from ring to pole.

Run: .venv/bin/python benchmarks/bench_tsm.py
"""
from __future__ import annotations

import time
from pathlib import Path
import tempfile

import numpy as np

import bonecad
from bonecad.contours.curves import contour_curves
from bonecad.settings import Settings
from bonecad.splines.tspline import open_region, tsm
from bonecad.tspline_model import build_tspline_model
from bonecad.tspline_model.cage import model_cage

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "tibia"


def area_mm2(ts, n: int = 400) -> float:
    """Surface area by the midpoint rule on an n x n grid of the parameter domain."""
    (s0, s1), (t0, t1) = ts.mesh.s_range, ts.mesh.t_range
    s = s0 + (np.arange(n) + 0.5) / n * (s1 - s0)
    t = t0 + (np.arange(n) + 0.5) / n * (t1 - t0)
    ss, tt = (g.ravel() for g in np.meshgrid(s, t, indexing="ij"))
    d = ts.evaluate(ss, tt, order=1)
    return float(np.linalg.norm(np.cross(d.du, d.dv), axis=1).sum() * (s1 - s0) * (t1 - t0) / n**2)


def figures(name: str, bone, settings: Settings) -> None:
    frame = bonecad.anatomical_frame(bone)
    contours = contour_curves(bone, frame, settings=settings.curves)
    model = build_tspline_model(bone, frame, contours, settings=settings.tspline,
                                apex_hole_radius_mm=settings.curves.apex_hole_radius_mm)
    with tempfile.TemporaryDirectory() as tmp:
        clock = time.perf_counter()
        doc = model_cage(model)
        path = tsm.write(doc, Path(tmp) / "tspline.tsm")
        t_write = time.perf_counter() - clock
        clock = time.perf_counter()
        back = tsm.read(path)
        t_read = time.perf_counter() - clock
        size = path.stat().st_size
    exact = all(np.array_equal(getattr(doc, k), getattr(back, k)) for k in ("links", "intervals", "grips", "faces"))
    info = tsm.census(back)
    ts = model.tspline
    period, lines, t_lines = ts.mesh.s_period, ts.mesh.s_lines, ts.mesh.t_lines
    s_a, s_b = lines[np.argmin(abs(lines - 0.7 * period))], lines[np.argmin(abs(lines - 0.25 * period))] + period
    t_a = t_lines[np.argmin(abs(t_lines - 0.3 * t_lines[-1]))]
    t_b = t_lines[np.argmin(abs(t_lines - 0.6 * t_lines[-1]))]
    region, kind = open_region(ts, (s_a, s_b), (t_a, t_b))
    patch = tsm.to_tspline(tsm.parse(tsm.format_document(tsm.rhino_document(region))))
    rng = np.random.default_rng(0)
    s, t = rng.random(10_000) * (s_b - s_a), rng.random(10_000) * (t_b - t_a)
    diff = np.abs(patch.evaluate(s, t).points - ts.evaluate(s + s_a, t + t_a).points).max()
    tube_area = area_mm2(ts)
    cap_area = sum(area_mm2(c.tspline) for c in model.caps)
    reach = []
    for cap in model.caps:
        pts = cap.tspline.control_points
        reach.append(float(np.linalg.norm(pts - pts.mean(axis=0), axis=1).max()))
    print(f"{name:<24} {info.faces:>5} {info.edges:>5} {info.vertices:>5} {info.t_junctions:>4} "
          f"{len(info.star_points):>3} {size / 1024:>7.0f} {t_write:>6.2f} {t_read:>5.2f} {str(exact):>5} "
          f"{diff:>9.1e} {kind:>10} {cap_area:>8.1f} {100 * cap_area / (tube_area + cap_area):>7.3f} "
          f"{max(reach):>6.2f}")


def main() -> None:
    settings = Settings.load()
    print(f"{'model':<24} {'faces':>5} {'edges':>5} {'verts':>5} {'T':>4} {'*':>3} {'KiB':>7} {'write':>6} "
          f"{'read':>5} {'exact':>5} {'patch mm':>9} {'mesh':>10} {'cap mm2':>8} {'cap %':>7} {'r mm':>6}")
    figures("phantom", bonecad.phantom_tibia(), settings)
    for path in sorted(DATA.glob("*.stl")):
        figures(path.stem, bonecad.load_bone(path), settings)


if __name__ == "__main__":
    main()
