"""PNG of the contour curves over the mesh, anterior and posterior views, hidden parts dimmed."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.lines import Line2D

from bonecad.render.figures import VIEWS, new_figure, save_figure, render_mesh_values, screen_axes
from bonecad.contours.curves import ContourSet

REGION_COLOURS = {"distal": "tab:blue", "shaft": "tab:green", "proximal": "tab:red"}


def curves_png(path: str | Path, vertices: np.ndarray, faces: np.ndarray, contours: ContourSet) -> Path:
    """Draw every contour curve on the shaded mesh (both in bone coordinates, mm)."""
    frame = np.eye(3)  # bone coordinates: x lateral, y anterior, z proximal
    rasters = render_mesh_values(vertices, faces, np.zeros(len(vertices)), frame, VIEWS, height_px=700)
    left, right, bottom, top = rasters[0].extent_mm
    fig = new_figure(2, (right - left) / (top - bottom))
    axes = fig.subplots(1, 2)
    u = np.linspace(0.0, 1.0, 400)
    for ax, raster, view in zip(axes, rasters, VIEWS):
        shade = 0.35 + 0.6 * np.abs(raster.normal[..., 2])
        img = np.repeat(shade[..., None], 3, axis=2)
        img[~raster.mask] = 1.0
        ax.imshow(img, extent=raster.extent_mm, interpolation="nearest")
        screen = screen_axes(frame, view)
        h, w = raster.mask.shape
        pixel = (raster.extent_mm[3] - raster.extent_mm[2]) / h
        # one line per region and style (curves joined by NaN gaps): a few artists, not hundreds
        for region, colour in REGION_COLOURS.items():
            curves = [c for c in contours.all_curves() if c.region == region]
            if not curves:
                continue
            s = np.stack([c.curve(u) for c in curves]) @ screen.T  # (curves, samples, 3)
            col = np.clip(((s[..., 0] - raster.extent_mm[0]) / pixel).astype(int), 0, w - 1)
            row = np.clip(((raster.extent_mm[3] - s[..., 1]) / pixel).astype(int), 0, h - 1)
            visible = s[..., 2] >= raster.depth[row, col] - 1.5
            gap = np.full((len(curves), 1), np.nan)
            x = np.hstack([s[..., 0], gap]).ravel()
            y = np.hstack([s[..., 1], gap]).ravel()
            shown = np.hstack([np.where(visible, s[..., 0], np.nan), gap]).ravel()
            ax.plot(x, y, color=colour, lw=0.5, alpha=0.25)
            ax.plot(shown, y, color=colour, lw=1.0)
        ax.set_title(f"{view} view")
        ax.set_xlabel("mm")
    axes[0].set_ylabel("mm above the plafond centre")
    handles = [Line2D([], [], color=c, label=r) for r, c in REGION_COLOURS.items()]
    fig.legend(handles=handles, loc="lower center", ncol=3)
    fig.suptitle("Contour curves")
    return save_figure(fig, path)
