"""The femur's landmarks against five raters, and the left-right asymmetry of the femur pairs (issue 45).

On every landmarked femur of ../shared/data/femur_pairs (``landmarks.json``: five raters x four repeats),
the frame stage alone (``femur_frame`` on the mesh as read) and, per landmark, the distance of bonecad's
point from the raters' mean against the raters' own spread (the distance of the farthest rater's mean from
it): median and max error, the spread's median and range, and on how many femurs the error is within it.
Then the head centre against the centre of a sphere through all the raters' head points, and the
transepicondylar axis (LEC - MEC) against the raters' (degrees).

Then both femurs of every subject measured (``anatomy.femur_morphometry``): right minus left of the
maximal length, the anteversion and the neck-shaft angle, the asymmetry a contralateral template (the other
side mirrored) carries.

The landmarks' directions and offsets (``anatomy.femur_points``) are the raters' means on these same ten
femurs: the figures are in-sample. For the landmarks found by a ray in a fixed direction (head and condyle
points), a leave-one-out check follows: each femur's ray along the raters' mean direction on the nine
others.

Run: .venv/bin/python benchmarks/bench_femur_landmarks.py   (44 s on a loaded machine)
"""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np

from bonecad.anatomy.femur import femur_frame, fit_sphere
from bonecad.anatomy.femur_morphometry import ASYMMETRY, asymmetry, measure_femur
from bonecad.anatomy import femur_points
from bonecad.anatomy.femur_points import NAMES
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.mesh.intake import read_mesh_file
from bonecad.mesh.topology import merge_duplicate_vertices
from bonecad.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("BONECAD_DATA", ROOT.parent / "shared" / "data"))
PAIRS = DATA / "femur_pairs"
HEAD_POINTS = ("SFH", "AFH", "LFH", "PFH", "MFH", "IFH")


def load(path: Path) -> BoneMesh:
    """The mesh as read, duplicate vertices merged (no recognition: some femurs are over 500 mm)."""
    vertices, faces = merge_duplicate_vertices(*read_mesh_file(path))
    return BoneMesh(vertices=np.asarray(vertices, dtype=np.float64), faces=np.asarray(faces, dtype=np.int64),
                    source=str(path))


def main() -> int:
    landmarks_file = PAIRS / "landmarks.json"
    if not landmarks_file.is_file():
        print(f"{landmarks_file} is absent")
        return 1
    rated = json.loads(landmarks_file.read_text())
    settings = Settings.load()
    errors: dict[str, list[float]] = {name: [] for name in NAMES}
    bands: dict[str, list[float]] = {name: [] for name in NAMES}
    head_errors, tea_errors = [], []
    rays: dict[str, dict] = {}  # key -> (frames, raters' means): for the leave-one-out check
    for key in sorted(rated):
        subject, side = key.rsplit("_", 1)
        bone = load(PAIRS / f"VSD_{subject}_femur_{side}.stl")
        frame = femur_frame(bone, settings=settings.femur)
        raters = {name: np.asarray(entry["raters"], dtype=float) for name, entry in rated[key].items()}
        means = {}
        for name in NAMES:
            mean = raters[name].reshape(-1, 3).mean(axis=0)
            means[name] = mean
            errors[name].append(float(np.linalg.norm(frame.femur.points[name] - mean)))
            bands[name].append(float(np.linalg.norm(raters[name].mean(axis=1) - mean, axis=1).max()))
        rays[key] = {"frame": frame, "means": means, "mesh": (bone.work.vertices, bone.work.faces)}
        centre = fit_sphere(np.vstack([raters[n].reshape(-1, 3) for n in HEAD_POINTS]))[0]
        head_errors.append(float(np.linalg.norm(frame.femur.head.centre - centre)))
        theirs = means["LEC"] - means["MEC"]
        ours = frame.femur.points["LEC"] - frame.femur.points["MEC"]
        cos = theirs @ ours / np.linalg.norm(theirs) / np.linalg.norm(ours)
        tea_errors.append(float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))))

    n = len(rated)
    print(f"Landmarks on {n} femurs of {PAIRS} (error: distance from the raters' mean; band: the farthest "
          "rater's mean from it), mm")
    print(f"{'':6} {'median':>7} {'max':>6}  {'band median':>11} {'band range':>12}  {'within':>7}")
    total = 0
    for name in NAMES:
        e, b = np.array(errors[name]), np.array(bands[name])
        within = int((e <= b).sum())
        total += within
        print(f"{name:6} {np.median(e):7.2f} {e.max():6.2f}  {np.median(b):11.2f} {b.min():5.2f}-{b.max():5.2f}  "
              f"{within:>3}/{n}")
    print(f"within the band: {total} of {n * len(NAMES)}")
    print(f"head centre vs the raters' sphere: median {np.median(head_errors):.2f}, max {max(head_errors):.2f} mm "
          f"({sum(e < 1.0 for e in head_errors)}/{n} within 1 mm)")
    print(f"transepicondylar axis vs the raters': {', '.join(f'{a:.1f}' for a in tea_errors)} deg "
          f"(median {np.median(tea_errors):.1f}, {sum(a < 3.0 for a in tea_errors)}/{n} within 3 deg)")

    leave_one_out(rays, bands)

    print("\nLeft-right asymmetry (right minus left), both femurs of a subject")
    print(f"{'subject':8} " + " ".join(f"{name:>22}" for name in ASYMMETRY))
    diffs = []
    subjects = sorted({p.stem.split("_")[1] for p in PAIRS.glob("VSD_*_femur_*.stl")})
    for subject in subjects:
        paths = {s: PAIRS / f"VSD_{subject}_femur_{s}.stl" for s in ("l", "r")}
        if not all(p.is_file() for p in paths.values()):
            continue
        measured = {}
        for s, p in paths.items():
            bone = load(p)
            measured[s] = measure_femur(bone, femur_frame(bone, settings=settings.femur))
        d = asymmetry(measured["l"], measured["r"])
        diffs.append([d[name] for name in ASYMMETRY])
        print(f"{subject:8} " + " ".join(f"{d[name]:22.1f}" for name in ASYMMETRY))
    a = np.abs(np.array(diffs))
    print(f"{'|median|':8} " + " ".join(f"{v:22.1f}" for v in np.median(a, axis=0)))
    print(f"{'|max|':8} " + " ".join(f"{v:22.1f}" for v in a.max(axis=0)))
    return 0


def _ray_starts(frame, mesh) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """landmark -> (ray start, frame rows) of the ray-found landmarks of ``femur_points``."""
    lm = frame.femur
    hip = femur_points._hip_frames(lm.head, lm.neck_axis[1], lm.knee_centre, frame.axes[1])
    distal = femur_points.distal_frame(*mesh, lm.knee_centre, frame.axes, lm.condyle_centres)
    out = {name: (lm.head.centre, hip[which]) for name, (which, _) in femur_points._HEAD_RAYS.items()}
    out.update({name: (lm.condyle_centres[i], distal) for name, (i, _) in femur_points._CONDYLE_RAYS.items()})
    return out


def leave_one_out(rays: dict[str, dict], bands: dict[str, list[float]]) -> None:
    """Each ray-found landmark with its direction the raters' mean on the other femurs."""
    keys = sorted(rays)
    starts = {k: _ray_starts(rays[k]["frame"], rays[k]["mesh"]) for k in keys}
    print("\nLeave-one-out (ray directions from the other nine femurs): median / max error, within the band")
    for name in (*femur_points._HEAD_RAYS, *femur_points._CONDYLE_RAYS):
        local = {}
        for k in keys:
            start, rows = starts[k][name]
            d = rays[k]["means"][name] - start
            local[k] = rows @ (d / np.linalg.norm(d))
        errors, within = [], 0
        for j, k in enumerate(keys):
            direction = np.mean([local[o] for o in keys if o != k], axis=0)
            start, rows = starts[k][name]
            v, f = rays[k]["mesh"]
            point = femur_points._ray_exit(v, f, start, direction @ rows, 100.0)
            errors.append(float(np.linalg.norm(point - rays[k]["means"][name])))
            within += errors[-1] <= bands[name][j]
        print(f"{name:6} {np.median(errors):6.2f} {max(errors):6.2f}  {within:>3}/{len(keys)}")


if __name__ == "__main__":
    sys.exit(main())
