"""Whole-pipeline benchmark: `reconstruct` (both models, analysis, exports) on the 120 k-triangle TLEM2
tibia; target <= 20 s on two cores and <= 2 GB. Prints every stage's time (a background job's own time:
they overlap, so they do not add up to the total) and the peak memory of the process and of its
background child (they run at the same time, so the sum bounds the peak of the two)."""
from __future__ import annotations

import resource
import sys
import tempfile
import time
from pathlib import Path

import bonecad

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "tibia"


def main() -> None:
    path = DATA / (sys.argv[1] if len(sys.argv) > 1 else "TLEM2_CT_tibia_r.stl")
    if not path.exists():
        sys.exit(f"benchmark needs {path}")
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        result = bonecad.reconstruct(path, out)
        total = time.perf_counter() - start
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    child_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    for stage, seconds in result.timings_s.items():
        print(f"{stage:<32} {seconds:7.2f} s")
    print(f"{'total (wall)':<32} {total:7.2f} s  (target <= 20 s)")
    print(f"{'peak memory':<32} {peak_mb:7.0f} MB + {child_mb:.0f} MB in the background child "
          f"(target <= 2048 MB together)")
    for name, report in result.reports.items():
        stats = report.deviation.mesh_to_cad.stats
        print(f"{name}: {report.info.get('faces')} faces, {report.info.get('control_points')} control points, "
              f"RMS {stats.rms_mm:.3f} mm")


if __name__ == "__main__":
    main()
