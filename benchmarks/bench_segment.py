"""Benchmark of CT segmentation: a 512 x 512 x 800 volume, and the real-mesh round trips.

1. A synthetic CT of a real tibia + fibula (0.5 mm voxels, 30 HU noise) is
   embedded in a 512 x 512 x 800 volume of air and written as NIfTI; a fresh
   process reads it and segments the tibia, reporting seconds and peak RSS
   (targets: segmentation under 30 s, under 4 GB).
2. For each mesh in ../shared/data/tibia: mesh -> CT (0.5 mm, 30 HU) ->
   segmented mesh, symmetric RMS distance to the tibia body (target 0.3 mm).

Run: python benchmarks/bench_segment.py [--only-large | --only-round-trips]
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

from bonecad.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
TIBIA_DIR = ROOT.parent / "shared" / "data" / "tibia"
LARGE_SHAPE = (800, 512, 512)  # (slices, rows, columns)
VOXEL_MM = 0.5


def _peak_rss_mb() -> float:
    """This process's peak RSS, MB: VmHWM (ru_maxrss would carry the parent's peak across fork + exec)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def make_large_volume(path: Path, mesh_path: Path) -> None:
    """Write the 512 x 512 x 800 NIfTI: the phantom of ``mesh_path`` centred in air (with noise)."""
    import trimesh

    from bonecad.imaging.phantom import AIR_HU, mesh_to_ct
    from bonecad.imaging.volume import CTVolume, write_nifti

    mesh = trimesh.load(mesh_path)
    leg = mesh_to_ct(mesh.vertices, mesh.faces, voxel_mm=VOXEL_MM, noise_hu=30.0, margin_mm=15.0)
    if any(n > m for n, m in zip(leg.shape, LARGE_SHAPE)):
        raise SystemExit(f"phantom {leg.shape} does not fit in {LARGE_SHAPE}")
    rng = np.random.default_rng(1)
    hu = np.empty(LARGE_SHAPE, dtype=np.float32)
    for k in range(LARGE_SHAPE[0]):
        hu[k] = AIR_HU + 30.0 * rng.standard_normal(LARGE_SHAPE[1:], dtype=np.float32)
    start = [(m - n) // 2 for n, m in zip(leg.shape, LARGE_SHAPE)]
    hu[tuple(slice(s, s + n) for s, n in zip(start, leg.shape))] = leg.hu
    affine = leg.affine.copy()
    affine[:3, 3] -= np.asarray(start[::-1]) * VOXEL_MM  # index (i, j, k) order
    write_nifti(CTVolume(hu=hu, affine=affine), path)


def segment_file(path: Path) -> dict:
    """Read and segment ``path`` in this process; seconds and peak RSS (MB)."""
    from bonecad.imaging.segment import segment_bone
    from bonecad.imaging.volume import read_volume

    t0 = time.perf_counter()
    volume = read_volume(path)
    t1 = time.perf_counter()
    rss_read = _peak_rss_mb()
    settings = Settings.load()
    mesh = segment_bone(volume, settings=settings.imaging, mesh_settings=settings.mesh)
    t2 = time.perf_counter()
    return {
        "shape": list(volume.shape),
        "read_s": round(t1 - t0, 2),
        "segment_s": round(t2 - t1, 2),
        "peak_rss_after_read_mb": round(rss_read),
        "peak_rss_mb": round(_peak_rss_mb()),
        "triangles": mesh.triangle_count,
        "watertight": mesh.watertight,
    }


def bench_large() -> dict:
    mesh_path = TIBIA_DIR / "TLEM2_CT_tibia_r.stl"
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "leg_512x512x800.nii"
        t0 = time.perf_counter()
        make_large_volume(path, mesh_path)
        made = time.perf_counter() - t0
        run = subprocess.run(
            [sys.executable, __file__, "--segment-file", str(path)], capture_output=True, text=True, check=True
        )
        result = json.loads(run.stdout.strip().splitlines()[-1])
    result["make_volume_s"] = round(made, 1)
    result["source_mesh"] = mesh_path.name
    return result


def bench_round_trips() -> list[dict]:
    import trimesh

    from bonecad.imaging.compare import round_trip

    settings = Settings.load()
    rows = []
    for path in sorted(TIBIA_DIR.glob("*.stl")):
        trip = round_trip(trimesh.load(path), settings=settings.imaging, mesh_settings=settings.mesh,
                          voxel_mm=VOXEL_MM, noise_hu=30.0)
        d = trip.distance
        rows.append(
            {
                "mesh": path.name,
                "ct_shape": list(trip.ct_shape),
                "rms_mm": round(d.rms_mm, 3),
                "mean_mm": round(d.mean_mm, 3),
                "max_mm": round(d.max_mm, 2),
                "centroid_shift_mm": round(d.centroid_shift_mm, 3),
                "phantom_s": round(trip.phantom_seconds, 1),
                "segment_s": round(trip.segment_seconds, 1),
                "pass_0.3mm": d.rms_mm <= 0.3,
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--segment-file", type=Path, help=argparse.SUPPRESS)
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--only-large", action="store_true")
    group.add_argument("--only-round-trips", action="store_true")
    args = parser.parse_args()
    if args.segment_file:
        print(json.dumps(segment_file(args.segment_file)))
        return
    if not TIBIA_DIR.is_dir():
        raise SystemExit(f"real meshes folder {TIBIA_DIR} is absent")
    if not args.only_round_trips:
        large = bench_large()
        print("512x512x800 segmentation:", json.dumps(large), flush=True)
        ok = large["segment_s"] < 30 and large["peak_rss_mb"] < 4096
        print(f"  target <30 s, <4 GB: {'met' if ok else 'MISSED'}", flush=True)
    if not args.only_large:
        rows = bench_round_trips()
        worst = max(r["rms_mm"] for r in rows)
        print(f"round trips at {VOXEL_MM} mm: worst RMS {worst:.3f} mm (target 0.3 mm)", flush=True)


if __name__ == "__main__":
    main()
