"""The before/after figure of a fracture reduction: the fragments as given and as reduced, from the front and
the side of the bone's long axis (orthographic projections of their vertices, one colour per fragment)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from bonecad.render.figures import save_figure

COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")


def reduction_png(path: str | Path, before: list[tuple[np.ndarray, np.ndarray]],
                  after: list[tuple[np.ndarray, np.ndarray]], labels: list[str], up: np.ndarray,
                  template: tuple[np.ndarray, np.ndarray] | None = None, title: str = "") -> Path:
    """Before (left two panels) and after (right two): each fragment's vertices (mm) projected on the planes
    through the long axis ``up`` (unit), ``template`` (its vertices in the reduced place, grey) behind them."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    up = np.asarray(up, dtype=np.float64)
    helper = np.array([1.0, 0, 0]) if abs(up[0]) < 0.9 else np.array([0, 1.0, 0])
    across = np.cross(up, helper)
    across /= np.linalg.norm(across)
    other = np.cross(up, across)
    fig = Figure(figsize=(11, 8), dpi=110)
    axes = fig.subplots(1, 4)
    panels = [(before, across, "as given, front"), (before, other, "as given, side"),
              (after, across, "reduced, front"), (after, other, "reduced, side")]
    for ax, (meshes, horizontal, name) in zip(axes, panels):
        if template is not None and meshes is after:
            pts = template[0][:: max(1, len(template[0]) // 20000)]
            ax.scatter(pts @ horizontal, pts @ up, s=0.3, c="0.82", linewidths=0, label="template")
        for k, ((vertices, _), label) in enumerate(zip(meshes, labels)):
            pts = vertices[:: max(1, len(vertices) // 15000)]
            ax.scatter(pts @ horizontal, pts @ up, s=0.4, c=COLOURS[k % len(COLOURS)], linewidths=0, label=label)
        ax.set_aspect("equal")
        ax.set_title(name, fontsize=10)
        ax.set_xlabel("mm")
    axes[0].set_ylabel("mm along the long axis")
    handles, names = axes[2].get_legend_handles_labels()
    fig.legend(handles, names, loc="lower center", ncol=len(names), markerscale=12, frameon=False)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout(rect=(0, 0.05, 1, 0.96))
    return save_figure(fig, path)
