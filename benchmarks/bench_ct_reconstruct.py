"""CT versus mesh input: a real tibia -> synthetic CT (0.5 mm voxels, 30 HU noise) -> segmentation ->
NURBS model, compared with the NURBS model built from the mesh itself. Target: deviation figures within
0.1 mm of each other. Both models are measured against the original mesh."""
from __future__ import annotations

import sys
import time
from pathlib import Path

import bonecad
from bonecad.analysis.deviation import shape_deviation
from bonecad.analysis.model import region_labels, tessellation_settings
from bonecad.analysis.statistics import settings_band_edges
from bonecad.contours.curves import contour_curves
from bonecad.imaging import mesh_to_ct, segment_bone
from bonecad.nurbs_model.model import build_nurbs
from bonecad.occ.tessellate import tessellate
from bonecad.settings import Settings

#: the shipped settings; their [analysis] tessellation tolerances and histogram bands (mm)
SETTINGS = Settings.load()
TESSELLATION = tessellation_settings(SETTINGS.analysis)
BANDS_MM = settings_band_edges(SETTINGS.analysis)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "tibia"


def figures(model_bone, reference, reference_frame):
    frame = bonecad.anatomical_frame(model_bone, SETTINGS)
    shape = build_nurbs(contour_curves(model_bone, frame, settings=SETTINGS.curves), settings=SETTINGS.nurbs).shape
    stats = shape_deviation(reference.vertices, reference.faces, tessellate(shape, TESSELLATION),
                            regions=region_labels(reference_frame), edges_mm=BANDS_MM,
                            sample_points=100_000).mesh_to_cad.stats
    return {"rms": stats.rms_mm, "p99": float(stats.abs_percentiles_mm[3]),
            "max": max(stats.max_outside_mm, stats.max_inside_mm)}


def main() -> None:
    names = sys.argv[1:] or ["LHDL_CT_tibia_no_fib_r.stl", "TLEM2_CT_tibia_r.stl"]
    print(f"{'mesh':<26} {'input':<5} {'RMS mm':>7} {'p99 mm':>7} {'max mm':>7}   segment s")
    for name in names:
        path = DATA / name
        if not path.exists():
            sys.exit(f"benchmark needs {path}")
        bone = bonecad.load_bone(path, settings=SETTINGS)
        frame = bonecad.anatomical_frame(bone, SETTINGS)
        from_mesh = figures(bone, bone, frame)
        start = time.perf_counter()
        segmented = segment_bone(mesh_to_ct(bone.vertices, bone.faces, voxel_mm=0.5, noise_hu=30.0),
                                 settings=SETTINGS.imaging, mesh_settings=SETTINGS.mesh)
        seconds = time.perf_counter() - start
        from_ct = figures(segmented, bone, frame)
        for label, f in (("mesh", from_mesh), ("CT", from_ct)):
            print(f"{path.stem:<26} {label:<5} {f['rms']:7.3f} {f['p99']:7.3f} {f['max']:7.3f}"
                  + (f"   {seconds:.1f}" if label == "CT" else ""))
        worst = max(abs(from_ct[k] - from_mesh[k]) for k in ("rms", "p99"))
        print(f"{'':<26} RMS/p99 differ by at most {worst:.3f} mm (target 0.1 mm)")


if __name__ == "__main__":
    main()
