"""Scale benchmark: `bonecad reconstruct` wall time and peak memory against the input's triangle count.

Targets (issue 24): 2 M triangles <= 15 s and <= 2.5 GB, 8 M <= 45 s and <= 6 GB on
two cores; the 100 k case not slower than before; the deviation of the models
against the full mesh within 0.2 percentage points of the 100 k case's.

The inputs are one real tibia (TLEM2 by default, ~120 k triangles) split at its
edge midpoints 1, 2 and 3 times (x4 triangles each: the same surface, shorter
edges), written as binary STL into a temporary folder (never the repository).
Each size runs ``bonecad reconstruct MESH --out DIR -q`` in new processes:
``--runs`` times timed (wall and CPU: their medians, and every run's wall time,
as a dense mesh's first touch of fresh memory costs a hypervisor fault whose
price drifts with the host: TLEM2 split 16-fold took 17.2-21.3 s in one
afternoon), then once watched for memory, the peak of the
whole process tree's proportional set size (PSS: forked children share their
parent's pages and count them once), polled every 0.1 s (the poll costs CPU
on the same cores: see ``reconstruct``). Per stage: the stage times of report.json (a background job's own time:
jobs overlap, so they do not add up to the wall time), and the share of the mesh
within 0.1, 0.2, 0.25 and 0.3 mm of each model and the RMS (mesh -> CAD, against the full input).

The report's figures come from 100 k area-weighted samples of each input, drawn
anew on each tessellation of the surface: a share near 90 % (within 0.1 mm) then
carries a sampling error of 0.1 percentage points, and two sizes' shares differ
by 0.13 points (one standard error) with identical models. So each run's models
are measured again, re-read from their STEP files, at the same 1 M samples of the
surface for every size (drawn on the level-0 tibia, which the subdivided meshes
follow exactly): those figures differ between sizes by the models alone (0.03
points of sampling error at 90 %).

Run: python benchmarks/bench_scale.py [--levels 0,1,2] [--mesh PATH] [--keep DIR] [--runs 3]
  --levels : subdivision levels to run (0: the mesh as read; 3: ~8 M triangles:
             run it alone on the machine, it needs several GB)
  --keep   : write (or reuse) the subdivided meshes in DIR instead of a temporary folder
  --runs   : timed runs per size (3)
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "tibia"

#: the report's stage timings grouped into the issue's stages (a stage absent from a run counts 0)
STAGE_GROUPS = {
    "intake": ["input"],
    "frame": ["anatomical frame"],
    "curves": ["contour curves"],
    "nurbs": ["NURBS model"],
    "nurbs analysis": ["NURBS analysis"],
    "tspline": ["T-spline model"],
    "tspline analysis": ["T-spline analysis"],
}


def subdivided_mesh(source: Path, level: int, folder: Path) -> Path:
    """``source`` split ``level`` times at its edge midpoints, as a binary STL in ``folder`` (reused if there)."""
    import trimesh

    from bonecad.mesh.sampling import midpoint_subdivision

    path = folder / f"{source.stem}_x{4 ** level}.stl"
    if path.exists():
        return path
    mesh = trimesh.load(source, force="mesh")  # merged vertices: the midpoints are shared by both triangles
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    for _ in range(level):
        vertices, faces = midpoint_subdivision(vertices, faces)
    trimesh.Trimesh(vertices, faces, process=False).export(path)
    return path


def _tree_pss_bytes(proc: psutil.Process) -> int:
    """Proportional set size of a process and its descendants (bytes); 0 for ones gone meanwhile."""
    total = 0
    for p in [proc, *proc.children(recursive=True)]:
        try:
            total += p.memory_full_info().pss
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            pass
    return total


def reconstruct(mesh: Path, out: Path, *, watch_memory: bool = False) -> tuple[float, float, float | None]:
    """Run ``bonecad reconstruct`` on ``mesh`` into ``out``; (wall s, CPU s of the process tree, peak PSS of
    the process tree GB when ``watch_memory``, else None).

    Memory is watched in a run of its own: PSS is read by walking the processes' page tables
    (/proc/PID/smaps_rollup, charged to the reader), 23 ms for a 4 GB process tree; polled every 0.1 s
    it took 7.7 s of CPU during a run of 8 M triangles on the same two cores, 47.9 s wall against 41.9 s
    unwatched."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "bonecad.run.cli", "reconstruct", str(mesh), "--out", str(out),
                             "-q"], stdout=subprocess.DEVNULL, cwd=out.parent)  # no bonecad/ in the current folder
    watched = psutil.Process(proc.pid)
    peak = 0
    while proc.poll() is None:
        if watch_memory:
            try:
                peak = max(peak, _tree_pss_bytes(watched))
            except psutil.NoSuchProcess:
                break
        time.sleep(0.1)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        sys.exit(f"bonecad reconstruct {mesh} failed (exit {proc.returncode})")
    cpu = after.ru_utime + after.ru_stime - usage.ru_utime - usage.ru_stime
    return wall, cpu, peak / 1e9 if watch_memory else None


def stage_seconds(report: dict) -> dict[str, float]:
    timings = report["timings_s"]
    return {group: sum(timings.get(name, 0.0) for name in names) for group, names in STAGE_GROUPS.items()}


def share_within(histogram: dict, limit_mm: float) -> float:
    """Share of the surface in the histogram's bands within +-``limit_mm`` (a band edge)."""
    edges = np.asarray(histogram["edges_mm"])
    shares = np.asarray(histogram["shares"])[1:-1]  # the bands, without under- and overflow
    return float(shares[(edges[:-1] >= -limit_mm - 1e-9) & (edges[1:] <= limit_mm + 1e-9)].sum())


def deviation_figures(report: dict) -> dict[str, tuple[float, ...]]:
    """Per model, mesh -> CAD: shares of the surface within 0.1, 0.2, 0.25 (the tolerance) and 0.3 mm of the
    model (0.2 and 0.3: the histogram's band edges; 0.1 and 0.25: the report's summary) and the RMS (mm)."""
    out = {}
    for name, model in report["models"].items():
        m2c = model["deviation"]["mesh_to_cad"]
        within = report["summary"][name]["within_mm"]
        out[name] = (within["0.1"], share_within(m2c["histogram"], 0.2), within["0.25"],
                     share_within(m2c["histogram"], 0.3), m2c["stats"]["rms_mm"])
    return out


#: samples of the common surface the models of every size are measured at (see the module doc)
COMMON_SAMPLES = 1_000_000


def tibia_of(mesh: Path):
    """The tibia of ``mesh`` as bonecad keeps it (its vertices and faces, mm)."""
    from bonecad.run.pipeline import load_input
    from bonecad.settings import Settings

    bone = load_input(mesh, Settings.load())
    return bone.vertices, bone.faces


def common_figures(out: Path, tibia) -> dict[str, tuple[float, ...]]:
    """Per model of ``out``: the shares of the common surface samples (``COMMON_SAMPLES`` on ``tibia``,
    seeded) within 0.1, 0.2, 0.25 and 0.3 mm of the model re-read from its STEP file, and the RMS (mm)."""
    from bonecad.analysis.deviation import shape_deviation
    from bonecad.analysis.model import tessellation_settings
    from bonecad.analysis.statistics import settings_band_edges
    from bonecad.occ.exchange import read_step
    from bonecad.occ.tessellate import tessellate
    from bonecad.settings import Settings

    analysis = Settings.load().analysis
    figures = {}
    for name in ("nurbs", "tspline"):
        step = out / f"{name}.step"
        if not step.exists():
            continue
        solid = read_step(step).solids()[0].wrapped
        m2c = shape_deviation(*tibia, tessellate(solid, tessellation_settings(analysis)),
                              sample_points=COMMON_SAMPLES, edges_mm=settings_band_edges(analysis)).mesh_to_cad
        figures[name] = (*(m2c.share_within(limit) for limit in (0.1, 0.2, 0.25, 0.3)), m2c.stats.rms_mm)
    return figures


def figure_cells(figures: dict[str, tuple[float, ...]], models: list[str]) -> list[str]:
    """One table cell per model: its shares (%) within 0.1 / 0.2 / 0.25 / 0.3 mm and its RMS (mm), or "-"."""
    return [" / ".join(f"{100 * share:.2f}" for share in figures[m][:-1]) + f", {figures[m][-1]:.4f}"
            if m in figures else "-" for m in models]


def wall_cell(walls: list[float]) -> str:
    """The median of the runs' wall times (s), then every run's in brackets."""
    return f"{np.median(walls):.1f} ({' / '.join(f'{w:.1f}' for w in walls)})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--levels", default="0,1,2", help="subdivision levels (0-3), comma-separated")
    parser.add_argument("--mesh", type=Path, default=DATA / "TLEM2_CT_tibia_r.stl")
    parser.add_argument("--keep", type=Path, help="folder for the subdivided meshes (default: temporary)")
    parser.add_argument("--runs", type=int, default=3, help="timed runs per size (their median is printed)")
    args = parser.parse_args()
    if not args.mesh.exists():
        sys.exit(f"benchmark needs {args.mesh}")
    levels = [int(x) for x in args.levels.split(",")]
    with tempfile.TemporaryDirectory(prefix="bench-scale-") as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        tibia = tibia_of(subdivided_mesh(args.mesh, 0, folder))
        rows, common = [], []
        for level in levels:
            mesh = subdivided_mesh(args.mesh, level, folder)
            out = Path(tmp) / f"out{level}"
            timed = [reconstruct(mesh, out) for _ in range(max(1, args.runs))]
            walls = sorted(run[0] for run in timed)
            cpu = float(np.median([run[1] for run in timed]))
            peak_gb = reconstruct(mesh, Path(tmp) / f"watched{level}", watch_memory=True)[2]
            report = json.loads((out / "report.json").read_text())
            read = sum(body["triangles"] for body in report["input"]["bodies"])
            rows.append((read, report["input"]["triangles"], walls, cpu, peak_gb, stage_seconds(report),
                         deviation_figures(report)))
            common.append((read, common_figures(out, tibia)))
            print(f"{mesh.name}: {read} triangles ({rows[-1][1]} the tibia's), {wall_cell(walls)} s wall, "
                  f"{cpu:.1f} s CPU, {peak_gb:.2f} GB", file=sys.stderr, flush=True)
    groups = list(STAGE_GROUPS)
    models = sorted({m for row in rows for m in row[-1]})
    print("| triangles (file, cleaned) | tibia | wall s (runs) | CPU s | peak GB | " + " | ".join(groups) + " | "
          + " | ".join(f"{m} % within 0.1 / 0.2 / 0.25 / 0.3 mm, RMS mm" for m in models) + " |")
    print("|" + "---|" * (5 + len(groups) + len(models)))
    for read, triangles, walls, cpu, peak, stages, figures in rows:
        cells = [f"{read:,}", f"{triangles:,}", wall_cell(walls), f"{cpu:.1f}", f"{peak:.2f}",
                 *(f"{stages[g]:.1f}" for g in groups), *figure_cells(figures, models)]
        print("| " + " | ".join(cells) + " |")
    print(f"\nThe same models at the same {COMMON_SAMPLES:,} samples of the level-0 tibia:\n")
    print("| triangles | " + " | ".join(f"{m} % within 0.1 / 0.2 / 0.25 / 0.3 mm, RMS mm" for m in models) + " |")
    print("|" + "---|" * (1 + len(models)))
    for read, figures in common:
        print(f"| {read:,} | " + " | ".join(figure_cells(figures, models)) + " |")


if __name__ == "__main__":
    main()
