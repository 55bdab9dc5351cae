"""The curve plan: the contour curves and the region boundaries drawn on the bone, front and side views."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.lines import Line2D

from bonecad.render.figures import View, as_bytes, panel_figure, save_figure, render_mesh_values, screen_axes
from bonecad.contours.curves import ContourSet
from bonecad.settings import load_profile

REGION_COLOURS = {"distal": "tab:blue", "shaft": "tab:green", "proximal": "tab:red"}
#: the plan's views: from the front and from the lateral side (bone coordinates: x lateral for either side)
PLAN_VIEWS: tuple[View, ...] = ("anterior", "lateral")


def curves_png(path: str | Path, vertices: np.ndarray, faces: np.ndarray, contours: ContourSet, *,
               height_px: int = 1600) -> Path:
    """Draw every contour curve on the shaded mesh (both in bone coordinates, mm), hidden parts dimmed,
    and the region boundaries (heights above the frame's origin, mm: the bone profile's) as dashed lines."""
    frame = np.eye(3)  # bone coordinates: x lateral, y anterior, z proximal
    rasters = render_mesh_values(vertices, faces, np.zeros(len(vertices)), frame, PLAN_VIEWS, height_px=height_px)
    fig, axes = panel_figure(rasters, height_px, extra_width_px=170)
    u = np.linspace(0.0, 1.0, 400)
    bounds = {"distal / shaft": contours.frame.distal_boundary_mm,
              "shaft / proximal": contours.frame.proximal_boundary_mm}
    for ax, raster, view in zip(axes, rasters, PLAN_VIEWS):
        shade = 0.35 + 0.6 * np.abs(raster.normal[..., 2])
        img = np.repeat(shade[..., None], 3, axis=2)
        img[~raster.mask] = 1.0
        ax.imshow(as_bytes(img), extent=raster.extent_mm, interpolation="nearest")
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
        for name, height in bounds.items():
            ax.axhline(height, color="k", ls="--", lw=1.0)
            ax.annotate(f"{name}: {height:.1f} mm", (0.01, height), xycoords=("axes fraction", "data"),
                        xytext=(0, 3), textcoords="offset points", va="bottom", fontsize=9)
        ax.set_title(f"{view} view", y=1.0)  # (placed: matplotlib would measure the ticks for it)
        ax.set_xlabel("mm")
    axes[0].set_ylabel(f"mm above the {load_profile(contours.frame.bone).origin}")
    handles = [Line2D([], [], color=c, label=f"{r} curves") for r, c in REGION_COLOURS.items()]
    handles.append(Line2D([], [], color="k", ls="--", label="region boundary"))
    axes[-1].legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 0.6), fontsize=9)
    fig.suptitle(f"Curve plan: {len(contours.all_curves())} contour curves in three regions")
    return save_figure(fig, path)
