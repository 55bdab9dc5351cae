"""`bonecad fe` against element size: elements, quality, volume, mesh and solve time, axial and torsional
stiffness (homogeneous cortical modulus, first order), on a reconstruction's folder.

    python benchmarks/bench_fe.py RECONSTRUCTION_FOLDER [--model tspline] [--sizes 4 3 2] [--order 1]

Prints one row per size and writes bench_fe.json beside the folder's files (in --out if given). Times are
wall-clock seconds of one process; on a shared machine they say so.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from bonecad.fe.elasticity import solve_cases
from bonecad.fe.tets import quality_summary
from bonecad.occ.brep import volume_mm3
from bonecad.occ.exchange import read_named_step
from bonecad.run.tetmesh import mesh_step
from bonecad.settings import Settings


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--model", default="tspline", choices=["tspline", "nurbs"])
    ap.add_argument("--sizes", type=float, nargs="+", default=[4.0, 3.0, 2.0])
    ap.add_argument("--order", type=int, default=1, choices=[1, 2])
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    fe = Settings.load().fe
    step = args.folder / f"{args.model}.step"
    frame = json.loads((args.folder / "frame.json").read_text())["bone_frame"]
    origin, axis = np.array(frame["origin"]), np.array(frame["proximal"])
    axis /= np.linalg.norm(axis)
    brep = volume_mm3(read_named_step(step)[0])
    rows = []
    for size in args.sizes:
        start = time.perf_counter()
        mesh = mesh_step(step, size, args.order, curvature_elements=fe.curvature_elements,
                         min_size_share=fe.min_size_share, max_elements=fe.max_elements, netgen=fe.netgen)
        mesh_s = time.perf_counter() - start
        start = time.perf_counter()
        k = solve_cases(mesh.nodes, mesh.tets, np.full(len(mesh.tets), fe.cortical_modulus_mpa), fe.poisson, origin,
                        axis, fe.end_depth_mm, ("axial", "torsion"), order=args.order)
        solve_s = time.perf_counter() - start
        row = {"size_mm": size, "order": args.order, "elements": len(mesh.tets), "nodes": len(mesh.nodes),
               "sicn": quality_summary(mesh.sicn), "gamma": quality_summary(mesh.gamma),
               "volume_vs_brep": round(float(mesh.volumes().sum() / brep - 1.0), 5),
               "mesh_s": round(mesh_s, 1), "solve_s": round(solve_s, 1), "dofs": k["axial"].dofs,
               "axial_n_per_mm": round(k["axial"].solver, 1), "axial_beam": round(k["axial"].beam, 1),
               "torsion_nmm_per_rad": round(k["torsion"].solver), "torsion_beam": round(k["torsion"].beam)}
        rows.append(row)
        print(json.dumps(row), flush=True)
    out = (args.out or args.folder) / "bench_fe.json"
    out.write_text(json.dumps({"step": str(step), "brep_volume_mm3": brep, "rows": rows,
                               "note": "wall-clock seconds, one process, measured on a loaded 2-core machine"},
                              indent=2))


if __name__ == "__main__":
    main()
