"""Template T-mesh fit per tibia (share within 0.5 mm, max, RMS, CPU and wall time), and the shape model's
leave-one-out figures on the real tibias next to two baselines (issue 21).

    PYTHONPATH=. python benchmarks/bench_template.py [--phantoms N]

Per tibia (the real meshes in ../shared/data/tibia, the default phantom and N varied phantoms): frame,
contour curves and template fit, one BLAS thread. Then the real tibias as a tiny cohort: leave-one-out
generalisation (RMS distance of each bone's mesh from its rebuild with k modes of the others), the morph
from the length alone (regression of the others), and the baselines: the others' mean shape, and that
mean scaled by the bone's length over the others' mean length. The morph of a held-out real tibia
may extrapolate the others' length range: it is reported, not refused. "length_mm" of a real tibia is its
mechanical axis length (plateau centre to plafond centre, the frame's), until `bonecad measure` exists.
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import bonecad  # noqa: E402
from bonecad.analysis.shape_model import (baselines_mm, build_shape_model, generalisation_mm,  # noqa: E402
                                          held_surface, morph_weights, surface_distance_mm)
from bonecad.run.shapes import template_fit_bone  # noqa: E402
from bonecad.settings import Settings  # noqa: E402
from tests.cohorts import phantom_parameters  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "tibia"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--phantoms", type=int, default=4, help="varied phantoms to fit besides the default one")
    ap.add_argument("--exclude", nargs="*", default=[], help="real meshes (file stems) to leave out, e.g. "
                    "LHDL_CT_tibia_no_fib_r (the same tibia as LHDL_CT_tibia_r: its fibula is dropped at intake)")
    args = ap.parse_args()
    settings = Settings.load()
    print(f"template: {settings.template.s_intervals} s-intervals at the ends, {settings.template.shaft_s_intervals} "
          f"on the shaft; t intervals {settings.template.distal_t_intervals}/{settings.template.shaft_t_intervals}/"
          f"{settings.template.proximal_t_intervals}")
    print(f"{'tibia':<28} {'share<=0.5':>10} {'max mm':>7} {'rms mm':>7} {'fit cpu s':>9} {'all cpu s':>9} "
          f"{'wall s':>7}")
    real = {}
    with threadpool_limits(limits=1, user_api="blas"):
        cases = [(p.stem, lambda p=p: bonecad.load_bone(p)) for p in sorted(DATA.glob("*.stl"))
                 if p.stem not in args.exclude]
        cases += [("phantom (default)", lambda: bonecad.phantom_tibia())]
        cases += [(f"phantom varied {i}", lambda p=p: bonecad.phantom_tibia(p))
                  for i, p in enumerate(phantom_parameters(args.phantoms, seed=7, voxel_mm=1.0))]
        for name, make in cases:
            bone = make()
            cpu, wall = time.process_time(), time.perf_counter()
            fit, points, weights = template_fit_bone(bone, settings)
            cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
            print(f"{name:<28} {fit.share_within:>10.4f} {fit.max_mm:>7.3f} {fit.rms_mm:>7.3f} {fit.cpu_s:>9.2f} "
                  f"{cpu:>9.2f} {wall:>7.2f}", flush=True)
            if not name.startswith("phantom"):
                length = bonecad.anatomical_frame(bone).mechanical_length_mm
                real[name] = (fit, points, weights, length)
        if len(real) >= 3:
            _real_cohort(real, settings)


def _real_cohort(real: dict, settings: Settings) -> None:
    names = list(real)
    shapes = np.stack([real[n][0].control_points for n in names])
    lengths = np.array([real[n][3] for n in names])
    tpl, sm = settings.template, settings.shape_model
    held = [held_surface(real[n][0].control_points, tpl, real[n][1], real[n][2], samples=sm.surface_samples,
                         seed=sm.seed) for n in names]
    modes = list(range(1, len(names) - 1))
    gen = generalisation_mm(shapes, held, modes, sm, tpl)
    base = baselines_mm(shapes, lengths, held, tpl)
    morph = []
    for j in range(len(names)):
        others = [i for i in range(len(names)) if i != j]
        model = build_shape_model(shapes[others], [names[i] for i in others], {"length_mm": lengths[others]}, sm)
        cp = model.shape(morph_weights(model, {"length_mm": float(lengths[j])}, replace(sm, range_margin=np.inf)))
        morph.append(surface_distance_mm(cp, tpl, held[j].points, held[j].weights, (held[j].s, held[j].t)))
    print("\nreal tibias, leave-one-out (RMS mm from the held-out mesh; models of the other "
          f"{len(names) - 1}):")
    head = "".join(f"{f'{k} modes':>9}" for k in modes)
    print(f"{'held out':<28}{head}{'morph(L)':>9}{'mean':>9}{'mean*L':>9}")
    for j, n in enumerate(names):
        row = "".join(f"{g:>9.3f}" for g in gen[j])
        print(f"{n:<28}{row}{morph[j]:>9.3f}{base[j, 0]:>9.3f}{base[j, 1]:>9.3f}")
    row = "".join(f"{g:>9.3f}" for g in gen.mean(axis=0))
    print(f"{'mean':<28}{row}{np.mean(morph):>9.3f}{base[:, 0].mean():>9.3f}{base[:, 1].mean():>9.3f}")


if __name__ == "__main__":
    main()
