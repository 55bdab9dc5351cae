"""The plate's figure: the bone, plate and screws seen from the front of the plate and from its side, and the
fit (distance from the plate's underside to the bone) as a colour map (bone coordinates, mm)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from bonecad.staging import staged_file
from bonecad.tspline_model.plate import PlatePlan, _offset_points


def plate_png(path: Path, plan: PlatePlan, vertices: np.ndarray, title: str) -> Path:
    """plate.png: front and side views (bone vertices grey, the plate's outline, the screws from head to tip,
    exits red where a check fails) and the fit colour map; ``vertices`` in bone coordinates."""
    normal = np.mean(_offset_points(plan.underside, plan.centre_uv, 1.0, plan.outward)
                     - plan.centre_points(), axis=0)
    normal[2] = 0.0
    normal /= np.linalg.norm(normal)
    across = np.cross([0.0, 0.0, 1.0], normal)
    outline = _offset_points(plan.underside, np.vstack([plan.outline_uv, plan.outline_uv[:1]]),
                             plan.offset_mm, plan.outward)
    z0, z1 = outline[:, 2].min() - 25.0, outline[:, 2].max() + 25.0
    bone = vertices[(vertices[:, 2] > z0) & (vertices[:, 2] < z1)]
    fig = Figure(figsize=(13, 6.5), dpi=100)
    views = [("front (looking at the plate)", across), ("side (plate on the left)", -normal)]
    for index, (name, horizontal) in enumerate(views):
        ax = fig.add_subplot(1, 3, index + 1)
        ax.scatter(bone @ horizontal, bone[:, 2], s=0.3, c="0.75", rasterized=True)
        ax.plot(outline @ horizontal, outline[:, 2], color="tab:blue", lw=1.2, label="plate outline")
        for screw in plan.screws:
            line = np.array([screw.head, screw.tip])
            failing = bool(screw.warnings)
            ax.plot(line @ horizontal, line[:, 2], color="tab:red" if failing else "tab:green", lw=1.5)
            ax.plot(screw.exit @ horizontal, screw.exit[2], "o", ms=4, color="tab:red" if failing else "k")
            ax.annotate(str(screw.hole), (screw.head @ horizontal, screw.head[2]), fontsize=7, color="tab:blue")
        for height in plan.joint_heights_mm:
            if z0 < height < z1:
                ax.axhline(height, color="tab:orange", ls="--", lw=0.8)
                ax.axhline(height + np.sign(np.mean(outline[:, 2]) - height) * plan.settings.joint_margin_mm,
                           color="tab:orange", ls=":", lw=0.8)
        ax.set_aspect("equal")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("mm")
        ax.set_ylabel("height above the frame's origin (mm)")
    ax = fig.add_subplot(1, 3, 3)
    points = plan.fit_points
    shown = ax.scatter(points @ across, points[:, 2], c=plan.fit_distance_mm, s=2, cmap="viridis",
                       vmin=min(0.0, float(plan.fit_distance_mm.min())),
                       vmax=max(plan.settings.gap_mm + 1.0, float(plan.fit_distance_mm.max())), rasterized=True)
    for screw in plan.screws:
        ax.plot(screw.underside @ across, screw.underside[2], "o", mfc="none", mec="w",
                ms=2 * plan.settings.hole_diameter_mm)
    fig.colorbar(shown, ax=ax, label="underside to bone (mm, < 0 inside)")
    ax.set_aspect("equal")
    summary = plan.fit_summary()
    ax.set_title(f"fit: {100 * summary['share_within_gap_plus_mm']['0.5']:.1f} % within gap + 0.5 mm,\n"
                 f"largest gap {summary['largest_gap_mm']:.2f} mm, seat {plan.seat_mm:.2f} mm", fontsize=9)
    ax.set_xlabel("mm")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    with staged_file(path) as tmp:
        FigureCanvasAgg(fig).print_png(str(tmp))
    return path
