"""Can the T-spline fit tell a rough segmentation's bumps from bone shape? (issue 18, "Rough and noisy meshes")

The rough mesh of ``tests/rough.py`` (TLEM2's tibia with smooth Gaussian bumps of 1.5-3 mm radius, at
most 1 mm, decimated to 1.8 mm edges) against the clean tibias and femurs of ../shared/data, by two
noise estimates a general noise stop could rest on:

- roughness: the RMS residual of a quadric fitted over every fit point's neighbourhood of radius R
  (``local_noise_mm`` with as many neighbours as cover pi R^2 of surface), its 25th percentile and
  median over the bone: measurement noise covers the whole bone, shape features only part of it;
- hold-out: the fit refined on 80 % of the fit points, round by round, and the share of the other
  20 % within 0.25 mm: noise would show as a held-out share that stalls while the training share rises.

Measured (shared host; 26, 24 and 12 s CPU): the rough mesh's roughness (R 4 mm: 0.054 / 0.070 mm;
R 6 mm: 0.113 / 0.149 mm) equals the ICL MRI tibia's (0.063 / 0.084; 0.115 / 0.152 mm) and exceeds
the clean CT TLEM2 tibia's (0.032 / 0.052; 0.070 / 0.120 mm); its held-out share follows the training
share up every round (control points: training / held-out, 240: 0.551 / 0.538, 1424: 0.952 / 0.942,
2385: 0.993 / 0.990) as the clean TLEM2's does (240: 0.612 / 0.601, 1886: 0.994 / 0.993). These bumps
are smooth at the fit points' spacing, so held-out points generalise, and an MRI mesh is as rough: the
fit's noise stop ([tspline] noise_level_*, rough_noise_level_mm) counts both as rough by the lower
quartile at 6 mm (noise level: rough 0.113, ICL 0.115, TLEM2 0.070 mm), and stops only once the share
and the RMS hold (it then leaves the maximum unchased). Against the clean tibia under the rough mesh
(0.781 of it within 0.25 mm of the rough mesh) the share rises with every round (240: 0.565, 590: 0.737,
1424: 0.777, 2385: 0.782): the bumps are at the fit's scale, so a fit stopped earlier, at the noise's
RMS (0.211 mm, round 2), lies farther from the bone, not nearer. (A voxel staircase is told apart by
its lattice, ``voxel_step_mm``.)

Run: python benchmarks/bench_noise.py [NAME ...]  (names: rough, or stems of ../shared/data/{tibia,femur})
"""
from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bonecad.run.bones import bone_settings  # noqa: E402
from bonecad.run.pipeline import frame_and_contours, load_input  # noqa: E402
from bonecad.settings import Settings  # noqa: E402
from bonecad.splines.tspline.fit import fit_adaptive, initial_parameters, local_noise_mm, noise_level_mm  # noqa: E402
from bonecad.tspline_model.model import fit_points, hole_masks, ring_constraints, tolerances  # noqa: E402
from bonecad.tspline_model.skinning import initial_mesh, parameterisation, skin  # noqa: E402
from tests.rough import build_rough  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
CLEAN = ("TLEM2_CT_tibia_r", "LHDL_CT_tibia_r", "ICL_MRI_tibia_r", "LHDL_CT_femur_r", "TLEM2_CT_femur_r",
         "ICL_MRI_femur_r")
RADII_MM = (4.0, 6.0)
HOLD_OUT, ROUNDS = 0.2, (0, 2, 4, 6, 8)


def clean_samples(name: str) -> np.ndarray | None:
    """Samples of the clean tibia under the rough mesh (scanner coordinates, mm); None for a clean mesh."""
    if name != "rough":
        return None
    rough = build_rough()
    clean = trimesh.Trimesh(rough.clean_vertices, rough.clean_faces, process=False)
    return trimesh.sample.sample_surface(clean, 60_000, seed=3)[0]


def mesh_path(name: str, folder: Path) -> Path:
    if name != "rough":
        return next(DATA.glob(f"*/{name}.stl"))
    rough = build_rough()
    path = folder / "rough.stl"
    trimesh.Trimesh(rough.vertices, rough.faces, process=False).export(path)
    return path


def roughness(points: np.ndarray, weights: np.ndarray) -> str:
    area = weights.sum() / len(points)
    cells = []
    for radius in RADII_MM:
        noise = local_noise_mm(points, neighbours=int(np.pi * radius**2 / area))
        cells.append(f"R {radius:g} mm: {np.quantile(noise, 0.25):.3f} / {np.median(noise):.3f}")
    return "; ".join(cells)


def hold_out(bone, frame, contours, settings: Settings, clean: np.ndarray | None = None) -> str:
    """Per round: control points, training / held-out share within 0.25 mm, and with ``clean`` ((m, 3)
    samples of the clean surface the mesh was made from, scanner coordinates) the share of them within
    0.25 mm of the fit (outside the apex holes, which the caps close)."""
    st = settings.tspline
    points, weights = fit_points(bone, frame, st)
    par = parameterisation(contours)
    radius = settings.curves.apex_hole_radius_mm
    hole_d, hole_p = hole_masks(points, frame, radius)
    keep = ~(hole_d | hole_p) & (weights > 0)
    held = np.random.default_rng(0).random(len(points)) < HOLD_OUT
    train, test = keep & ~held, keep & held
    mesh = initial_mesh(par, s_intervals=st.initial_s_intervals, t_spacing_mm=st.initial_t_spacing_mm,
                        apex_rows=st.apex_rows)
    ts0, _, _ = skin(contours, par, mesh, fairness=st.fairness_weight)
    s0, t0, _ = initial_parameters(ts0, points[train])
    within = st.target_share_within_mm[1]
    if clean is not None:
        clean = frame.to_bone(clean)
        clean = clean[~np.logical_or(*hole_masks(clean, frame, radius))]
    cells = []
    for rounds in ROUNDS:
        fit = fit_adaptive(ts0, points[train], weights[train], s=s0, t=t0,
                           tolerances=replace(tolerances(st), max_rounds=rounds), fairness=st.fit_fairness_weight,
                           constraints=ring_constraints(contours, par, radius))
        _, _, distance = initial_parameters(fit.tspline, points[test])
        cell = (f"{fit.tspline.n_control}: {fit.stats.share_within:.3f} / "
                f"{np.average(distance <= within, weights=weights[test]):.3f}")
        if clean is not None:
            cell += f" / clean {np.mean(initial_parameters(fit.tspline, clean)[2] <= within):.3f}"
        cells.append(cell)
        if fit.converged:
            break
    return "; ".join(cells)


def main(names: list[str]) -> None:
    import tempfile

    print("roughness: quadric RMS residual, 25th percentile / median (mm); noise level ([tspline]); hold-out: "
          "control points: training / held-out share within 0.25 mm (/ the clean tibia's under the rough mesh)")
    for name in names:
        with tempfile.TemporaryDirectory() as folder:
            start = time.process_time()
            settings = Settings.load()
            bone = load_input(mesh_path(name, Path(folder)), settings)
            settings = bone_settings(bone, settings)
            frame, contours, _ = frame_and_contours(bone, settings)
            points, weights = fit_points(bone, frame, settings.tspline)
            print(f"\n{name}: {len(points)} fit points")
            print(f"  roughness: {roughness(points, weights)}")
            st = settings.tspline
            level = noise_level_mm(points, weights, radius_mm=st.noise_level_radius_mm,
                                   quantile=st.noise_level_quantile)
            print(f"  noise level {level:.3f} mm: {'rough' if level >= st.rough_noise_level_mm else 'not rough'}")
            if name in ("rough", "TLEM2_CT_tibia_r"):
                print(f"  hold-out:  {hold_out(bone, frame, contours, settings, clean_samples(name))}")
            print(f"  {time.process_time() - start:.1f} s CPU", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:] or ["rough", *CLEAN])
