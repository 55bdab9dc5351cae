"""Cohort benchmark: ``run_cohort`` (what ``bonecad cohort`` runs) on N phantom tibias, default 100, 2 workers.

Target (issue 21): at least 6 bones per minute on 2 cores once the template fit is in the job. Prints the bones
per minute over the whole run (the local cluster's start and close included) and between the first and the last
bone (the steady rate), the workers' CPU seconds per bone (median, mean, max: each worker's own measure of the
bone), and this process's CPU with its children's (the workers). The phantoms (varied parameters, seed 0,
meshed at the shipped phantom's 1 mm) are made first on a cluster of the same size into ``--phantoms`` (kept,
so a second run skips them) and are not timed. The 2 cores are shared: compare the CPU figures, not the wall.

Run: python benchmarks/bench_cohort.py [--bones N] [--workers W] [--phantoms DIR] [--config TOML]
"""
from __future__ import annotations

import argparse
import resource
import statistics
import tempfile
import time
from pathlib import Path

from bonecad.run.cluster import DaskExecutor
from bonecad.run.cohort import run_cohort, write_phantom_cohort
from bonecad.settings import Settings


def cpu_s() -> float:
    """CPU seconds of this process and of its ended children (the local cluster's workers)."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bones", type=int, default=100)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--phantoms", type=Path, default=Path(tempfile.gettempdir()) / "bonecad-bench-cohort")
    parser.add_argument("--config", type=Path, help="TOML file overriding defaults (as bonecad's --config)")
    args = parser.parse_args()
    settings = Settings.load(args.config).replace("cohort", workers=args.workers)

    started = time.perf_counter()
    with DaskExecutor(workers=args.workers) as ex:
        write_phantom_cohort(args.phantoms, args.bones, settings, ex)
    print(f"{args.bones} phantoms in {args.phantoms} ({time.perf_counter() - started:.0f} s, not timed)")
    folder = Path(tempfile.mkdtemp(prefix="bench-cohort-"))
    for i in range(args.bones):  # the cohort's input: the first N phantoms, linked
        (folder / f"phantom_{i:03d}.stl").symlink_to(args.phantoms / f"phantom_{i:03d}.stl")

    ended: list[float] = []
    cpu0, started = cpu_s(), time.perf_counter()
    result = run_cohort(folder, folder / "out", settings,
                        progress=lambda n, total, record: ended.append(time.perf_counter()) if record else None)
    wall, cpu = time.perf_counter() - started, cpu_s() - cpu0
    per_bone = [r.cpu_s for r in result.records]
    print(f"{len(result.records)} bones, {args.workers} workers: {result.count('done')} done, "
          f"{result.count('bad input')} bad input, {result.count('failed')} failed")
    print(f"  wall {wall:.1f} s (first bone after {ended[0] - started:.1f} s): "
          f"{60 * len(result.records) / wall:.1f} bones/min over the run, "
          f"{60 * (len(ended) - 1) / max(ended[-1] - ended[0], 1e-9):.1f} bones/min first to last bone")
    print(f"  CPU per bone (the workers' measure): median {statistics.median(per_bone):.2f} s, "
          f"mean {statistics.mean(per_bone):.2f} s, max {max(per_bone):.2f} s")
    print(f"  CPU of the run (this process and the workers): {cpu:.1f} s, {cpu / len(result.records):.2f} s "
          f"per bone")


if __name__ == "__main__":
    main()
