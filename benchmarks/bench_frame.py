"""Frame benchmark: mesh intake and anatomical frame on the largest real tibia (target: frame < 3 s)."""
from __future__ import annotations

import resource
import sys
import time
from pathlib import Path

import bonecad

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "tibia"


def main() -> None:
    path = DATA / "TLEM2_CT_tibia_r.stl"  # 120 k triangles with its fibula
    if not path.exists():
        sys.exit(f"benchmark needs {path}")
    start = time.perf_counter()
    bone = bonecad.load_bone(path)
    loaded = time.perf_counter()
    frame = bonecad.anatomical_frame(bone)
    done = time.perf_counter()
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"input triangles      {sum(b.triangles for b in bone.bodies)}")
    print(f"intake (read+clean)  {loaded - start:.2f} s")
    print(f"anatomical frame     {done - loaded:.2f} s  (target < 3 s)")
    print(f"total                {done - start:.2f} s, peak RSS {peak_mb:.0f} MB, side {frame.side}")


if __name__ == "__main__":
    main()
