"""Fit stability: how far the T-spline's deviation figures move when its fit points' weights move a little.

Issue 24 asks a dense mesh's models to lie within 0.2 percentage points of the
100 k mesh's (share of the mesh within 0.1 mm and the other bands). This measures
what that comparison can resolve: the same mesh, the same frame, curves and fit
points, only the points' area weights multiplied by 1 + ``--scale`` x N(0, 1)
(seeded, a different draw per seed; seed 0: as shipped). The refinement's
choices (which elements to split, and which way) then differ once a marginal
element changes rank, and the T-mesh goes its own way from there: the spread of
the shares over the seeds is the figure's own repeatability on one mesh.

Each seed runs ``bonecad reconstruct MESH --out DIR -q`` in a new process (this
script with ``--one SEED OUT``: the weights perturbed in ``tspline_model.fit_points``,
which both the noise job and the fit call), then measures its T-spline, re-read
from its STEP file, at the same 1 M samples of the mesh (``bench_scale.common_figures``).

Run: python benchmarks/bench_fit_stability.py [--mesh PATH] [--seeds 4] [--scale 1e-3]
  (the README's figures: --seeds 6 --scale 0.05, and --seeds 6 at the default scale)
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench_scale import DATA, common_figures, tibia_of


def run_one(seed: int, scale: float, mesh: str, out: str) -> int:
    """``bonecad reconstruct`` of ``mesh`` into ``out``, the fit points' weights perturbed by ``seed``."""
    import bonecad.tspline_model.model as model
    from bonecad.run.cli import main

    shipped = model.fit_points

    def perturbed(bone, frame, settings):
        points, weights = shipped(bone, frame, settings)
        noise = np.random.default_rng(seed).standard_normal(len(weights))
        return points, weights * (1.0 + scale * noise) if seed else weights

    model.fit_points = perturbed
    return main(["reconstruct", mesh, "--out", out, "-q"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", type=Path, default=DATA / "TLEM2_CT_tibia_r.stl")
    parser.add_argument("--seeds", type=int, default=4, help="runs: seed 0 (as shipped), then 1, 2, ...")
    parser.add_argument("--scale", type=float, default=1e-3, help="relative SD of the weights' noise")
    parser.add_argument("--one", nargs=2, metavar=("SEED", "OUT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        sys.exit(run_one(int(args.one[0]), args.scale, str(args.mesh), args.one[1]))
    if not args.mesh.exists():
        sys.exit(f"benchmark needs {args.mesh}")
    tibia = tibia_of(args.mesh)
    print(f"{args.mesh.name}: fit point weights x (1 + {args.scale:g} N(0, 1)), T-spline at 1 M common samples")
    print("| seed | control points | fit rounds | % within 0.1 / 0.2 / 0.25 / 0.3 mm | RMS mm |")
    print("|---|---|---|---|---|")
    shares = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.seeds):
            out = Path(tmp) / f"seed{seed}"
            subprocess.run([sys.executable, __file__, "--mesh", str(args.mesh), "--scale", str(args.scale),
                            "--one", str(seed), str(out)], check=True, stdout=subprocess.DEVNULL, timeout=600)
            summary = json.loads((out / "tspline.json").read_text())["summary"]
            figures = common_figures(out, tibia)["tspline"]
            shares.append(figures[0])
            print(f"| {seed} | {summary['control_points']} | {len(summary['fit_history']) - 1} | "
                  + " / ".join(f"{100 * s:.2f}" for s in figures[:4]) + f" | {figures[4]:.4f} |")
    print(f"within 0.1 mm: spread {100 * (max(shares) - min(shares)):.2f} percentage points over {args.seeds} runs")


if __name__ == "__main__":
    main()
