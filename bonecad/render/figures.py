"""Offscreen images of surfaces: deviation colour maps and zebra stripes (no display needed).

Rendering is a numpy point-splatting z-buffer: the surface is sampled densely
(several samples per pixel, area-weighted), each sample is projected
orthographically, and the nearest sample per pixel wins. No OpenGL, no VTK, so
it runs the same on a headless CI machine. Figures are composed with
matplotlib's Agg backend.

Views are anatomical: the caller passes ``frame``, a (3, 3) rotation whose
columns are the lateral (x), anterior (y) and proximal (z) unit axes in model
coordinates. The anterior view looks from the front (along -y) with proximal
up; the posterior view looks from the back (along +y).

Zebra stripes (reflection lines): each pixel shows the reflection r of the view
direction about the exact surface normal; the stripe is
``floor(n_stripes * angle(r, stripe_axis) / pi) mod 2``, i.e. the reflection of
an environment of parallel light bands (Klass 1980, "Correction of local surface
irregularities using reflection lines", CAD 12(2), doi:10.1016/0010-4485(80)90021-5).
A position gap breaks a stripe, a tangent (G1) break makes stripes jump, a
curvature (G2) break makes them kink.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from matplotlib.figure import Figure

from bonecad.staging import staged_file
from bonecad.mesh.sampling import triangle_areas
from bonecad.analysis.deviation import sample_surface
from bonecad.mesh.tessellation import Tessellation

View = Literal["anterior", "posterior"]
VIEWS: tuple[View, ...] = ("anterior", "posterior")


@dataclass(frozen=True)
class Raster:
    """One rendered view.

    mask : (H, W) bool, pixel covered; depth : (H, W) float (nearer = larger)
    values : (H, W, k) per-pixel attributes of the frontmost sample
    normal : (H, W, 3) unit normals in screen axes (right, up, towards viewer)
    extent_mm : (left, right, bottom, top) of the image in screen mm
    """

    mask: np.ndarray
    depth: np.ndarray
    values: np.ndarray
    normal: np.ndarray
    extent_mm: tuple[float, float, float, float]


def check_frame(frame: np.ndarray) -> np.ndarray:
    """The frame as a (3, 3) float array; raise unless it is a rotation (right- or left-handed)."""
    f = np.asarray(frame, dtype=np.float64)
    if f.shape != (3, 3):
        raise ValueError(f"frame must be a (3, 3) matrix of axis columns, got shape {f.shape}")
    if not np.allclose(f.T @ f, np.eye(3), atol=1e-6):
        raise ValueError("frame columns must be orthonormal (lateral, anterior, proximal unit axes)")
    return f


def screen_axes(frame: np.ndarray, view: View) -> np.ndarray:
    """(3, 3) rows: screen right, screen up, towards the viewer, in model coordinates."""
    f = check_frame(frame)
    anterior, proximal = f[:, 1], f[:, 2]
    if view == "anterior":
        toward = anterior
    elif view == "posterior":
        toward = -anterior
    else:
        raise ValueError(f"view must be one of {VIEWS}, got {view!r}")
    right = np.cross(proximal, toward)  # forward = -toward; right = forward x up
    return np.stack([right, proximal, toward])


def splat(
    points: np.ndarray,
    normals: np.ndarray,
    values: np.ndarray,
    axes: np.ndarray,
    *,
    pixel_mm: float,
    bounds_mm: tuple[float, float, float, float],
) -> Raster:
    """Z-buffer ``points`` (N, 3) with ``normals`` (N, 3) and ``values`` (N, k) into pixels."""
    s = points @ axes.T
    left, right, bottom, top = bounds_mm
    width = int(np.ceil((right - left) / pixel_mm))
    height = int(np.ceil((top - bottom) / pixel_mm))
    col = np.clip(((s[:, 0] - left) / pixel_mm).astype(np.int64), 0, width - 1)
    row = np.clip(((top - s[:, 1]) / pixel_mm).astype(np.int64), 0, height - 1)
    pix = row * width + col
    # z-buffer: the nearest depth per pixel, then one sample reaching it per pixel
    # (the lowest index among exact ties); no sort of all samples
    z = s[:, 2]
    front = np.full(height * width, -np.inf)
    np.maximum.at(front, pix, z)
    reach = np.flatnonzero(z == front[pix])
    owner = np.full(height * width, len(z))
    np.minimum.at(owner, pix[reach], reach)
    first = owner[owner < len(z)]
    mask = np.zeros(height * width, dtype=bool)
    mask[pix[first]] = True
    depth = np.full(height * width, -np.inf)
    depth[pix[first]] = s[first, 2]
    vals = np.zeros((height * width, values.shape[1]))
    vals[pix[first]] = values[first]
    nrm = np.zeros((height * width, 3))
    nrm[pix[first]] = normals[first] @ axes.T
    raster = Raster(
        mask.reshape(height, width),
        depth.reshape(height, width),
        vals.reshape(height, width, -1),
        nrm.reshape(height, width, 3),
        (left, right, bottom, top),
    )
    return _fill_pinholes(_fill_pinholes(raster))


def _fill_pinholes(raster: Raster) -> Raster:
    """Fill uncovered pixels with at least 5 of 8 covered neighbours from the nearest neighbour.

    Random splatting leaves isolated empty pixels inside the surface; true
    silhouettes have fewer covered neighbours and stay as they are.
    """
    mask = raster.mask
    padded = np.pad(mask, 1)
    depth = np.pad(raster.depth, 1, constant_values=-np.inf)
    h, w = mask.shape
    shifts = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0)]
    count = sum(padded[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w].astype(int) for dy, dx in shifts)
    # a pixel the front surface missed shows a sample from behind: far deeper than
    # nearly all its neighbours (10 pixels); treat it as empty too
    pixel_mm = (raster.extent_mm[3] - raster.extent_mm[2]) / h
    nearer = sum(
        (depth[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w] > raster.depth + 10 * pixel_mm).astype(int)
        for dy, dx in shifts
    )
    hole = (~mask & (count >= 5)) | (mask & (nearer >= 6))
    if not hole.any():
        return raster
    best = np.full(mask.shape, -np.inf)
    src = np.zeros(mask.shape + (2,), dtype=np.int64)
    grid = np.indices(mask.shape)
    rows, cols = grid[0], grid[1]
    for dy, dx in shifts:
        d = depth[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
        better = d > best
        best = np.where(better, d, best)
        src[better] = np.stack([rows[better] + dy, cols[better] + dx], axis=1)
    r, c = np.nonzero(hole)
    sr, sc = src[r, c, 0], src[r, c, 1]
    out = [a.copy() for a in (raster.mask, raster.depth, raster.values, raster.normal)]
    out[0][r, c] = True
    for arr in out[1:]:
        arr[r, c] = arr[sr, sc]
    return Raster(out[0], out[1], out[2], out[3], raster.extent_mm)


def _view_bounds(vertices: np.ndarray, axes: np.ndarray, margin: float = 0.03):
    s = vertices @ axes.T
    lo, hi = s[:, :2].min(axis=0), s[:, :2].max(axis=0)
    pad = margin * (hi - lo).max()
    return (lo[0] - pad, hi[0] + pad, lo[1] - pad, hi[1] + pad)


def _dense_samples(vertices, triangles, pixel_mm: float, per_pixel: float, seed: int, cap: int = 2_000_000):
    area = triangle_areas(vertices, triangles).sum()
    count = int(min(cap, max(10_000, per_pixel * area / pixel_mm**2)))
    return sample_surface(vertices, triangles, count, seed=seed)


def render_mesh_values(
    vertices: np.ndarray,
    triangles: np.ndarray,
    vertex_values: np.ndarray,
    frame: np.ndarray,
    views: tuple[View, ...] = VIEWS,
    *,
    height_px: int = 800,
    seed: int = 0,
) -> list[Raster]:
    """Views of a triangle mesh with per-vertex scalars interpolated (values[..., 0]) and shading normals."""
    from bonecad.mesh.closest import vertex_normals

    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    vertex_values = np.asarray(vertex_values, dtype=np.float64)
    if vertex_values.shape != (len(vertices),):
        raise ValueError(f"vertex_values must be ({len(vertices)},), got {vertex_values.shape}")
    frames = [screen_axes(frame, v) for v in views]
    bounds = [_view_bounds(vertices, a) for a in frames]
    pixel = min((b[3] - b[2]) / height_px for b in bounds)
    samples = _dense_samples(vertices, triangles, pixel, 2.0, seed)
    tri = triangles[samples.triangle]
    vn = vertex_normals(vertices, triangles)
    normals = np.einsum("nk,nkj->nj", samples.barycentric, vn[tri])
    values = np.einsum("nk,nk->n", samples.barycentric, vertex_values[tri])[:, None]
    return [splat(samples.points, normals, values, a, pixel_mm=pixel, bounds_mm=b) for a, b in zip(frames, bounds)]


def render_tessellation_normals(
    tess: Tessellation,
    frame: np.ndarray,
    views: tuple[View, ...] = VIEWS,
    *,
    height_px: int = 800,
    seed: int = 0,
) -> list[Raster]:
    """Views of a tessellated shape with exact surface normals per pixel (for zebra).

    The tessellation is splatted with each sample's face and (u, v); the exact
    normal is then evaluated once per visible pixel (not per sample: about half
    the samples end up hidden or behind others). values = (face index, u, v).
    """
    frames = [screen_axes(frame, v) for v in views]
    bounds = [_view_bounds(tess.vertices, a) for a in frames]
    pixel = min((b[3] - b[2]) / height_px for b in bounds)
    samples = _dense_samples(tess.vertices, tess.triangles, pixel, 2.0, seed)
    tri = tess.triangles[samples.triangle]
    normals = np.einsum("nk,nkj->nj", samples.barycentric, tess.normals[tri])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)  # kept where no surface
    uv = np.einsum("nk,nkj->nj", samples.barycentric, tess.uv[tri])
    face = tess.triangle_face[samples.triangle]
    values = np.column_stack([face.astype(float), uv])
    rasters = [splat(samples.points, normals, values, a, pixel_mm=pixel, bounds_mm=b) for a, b in zip(frames, bounds)]
    sset = tess.packed_surfaces
    for raster, axes in zip(rasters, frames):
        rows, cols = np.nonzero(raster.mask)
        pix_face = raster.values[rows, cols, 0].astype(np.int64)
        has = np.flatnonzero(sset.group[pix_face] >= 0)
        f = pix_face[has]
        sample = sset.evaluate(f, raster.values[rows[has], cols[has], 1], raster.values[rows[has], cols[has], 2],
                               order=1)
        n = np.cross(sample.du, sample.dv)
        size = np.linalg.norm(n, axis=1, keepdims=True)
        good = size[:, 0] > 1e-12
        n = np.where(tess.reversed_faces[f][:, None], -n, n) / np.maximum(size, 1e-300)
        raster.normal[rows[has[good]], cols[has[good]]] = n[good] @ axes.T
    return rasters


def zebra_image(raster: Raster, *, stripes: int = 40, stripe_axis: str = "horizontal") -> np.ndarray:
    """(H, W, 3) RGB zebra image in [0, 1]; background white.

    ``stripe_axis``: 'horizontal' light bands run left-right (reflect about the
    screen up axis), 'vertical' run top-bottom.
    """
    n = raster.normal
    # a perspective eye in front of the object (2x its height away), so the
    # reflections vary across flat regions too and stripes are dense
    left, right, bottom, top = raster.extent_mm
    h, w = raster.mask.shape
    xs = left + (np.arange(w) + 0.5) * (right - left) / w
    ys = top - (np.arange(h) + 0.5) * (top - bottom) / h
    depth = np.where(raster.mask, raster.depth, 0.0)
    eye = np.array([(left + right) / 2, (bottom + top) / 2, depth[raster.mask].max(initial=0.0) + 2 * (top - bottom)])
    view = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], depth), axis=-1) - eye
    view /= np.maximum(np.linalg.norm(view, axis=-1, keepdims=True), 1e-300)
    r = view - 2.0 * np.sum(n * view, axis=-1)[..., None] * n
    axis = np.array([0.0, 1.0, 0.0]) if stripe_axis == "horizontal" else np.array([1.0, 0.0, 0.0])
    angle = np.arccos(np.clip(r @ axis, -1.0, 1.0))
    band = np.floor(stripes * angle / np.pi).astype(np.int64) % 2
    shade = 0.55 + 0.45 * np.abs(n[..., 2])
    grey = np.where(band == 0, 0.08, 0.95) * shade
    img = np.repeat(grey[..., None], 3, axis=2)
    img[~raster.mask] = 1.0
    return img


def new_figure(ncols: int, aspect: float):
    """A matplotlib Figure outside pyplot: no global backend switch (Jupyter's inline plots keep working)."""
    height = 7.0
    width = max(4.0, ncols * height * aspect + 1.6)
    return Figure(figsize=(width, height), dpi=110)


def save_figure(fig, path: str | Path) -> Path:
    path = Path(path)
    with staged_file(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


def deviation_map_png(
    path: str | Path,
    vertices: np.ndarray,
    triangles: np.ndarray,
    vertex_deviation_mm: np.ndarray,
    frame: np.ndarray,
    *,
    limit_mm: float | None = None,
    title: str = "Deviation (mesh - CAD), mm",
    height_px: int = 700,
) -> Path:
    """PNG of the mesh coloured by signed deviation, anterior and posterior views, scale bar in mm.

    Diverging map (red = mesh outside the CAD model, blue = inside), symmetric
    about 0, clipped at ``limit_mm`` (default: the 99th percentile of
    |deviation| rounded up to 0.05 mm, at least 0.05 mm).
    """
    d = np.asarray(vertex_deviation_mm, dtype=np.float64)
    if limit_mm is None:
        limit_mm = max(0.05, np.ceil(np.percentile(np.abs(d), 99) / 0.05) * 0.05)
    rasters = render_mesh_values(vertices, triangles, d, frame, VIEWS, height_px=height_px)
    r0 = rasters[0]
    aspect = (r0.extent_mm[1] - r0.extent_mm[0]) / (r0.extent_mm[3] - r0.extent_mm[2])
    fig = new_figure(2, aspect)
    from matplotlib import cm, colormaps, colors

    norm = colors.Normalize(vmin=-limit_mm, vmax=limit_mm)
    cmap = colormaps["RdBu_r"]
    axes = fig.subplots(1, 2)
    for ax, raster, name in zip(axes, rasters, VIEWS):
        rgb = cmap(norm(raster.values[..., 0]))[..., :3]
        shade = 0.45 + 0.55 * np.abs(raster.normal[..., 2])
        rgb = rgb * shade[..., None]
        rgb[~raster.mask] = 1.0
        ax.imshow(rgb, extent=raster.extent_mm, interpolation="nearest")
        ax.set_title(name)
        ax.set_xlabel("mm")
    axes[0].set_ylabel("mm (proximal up)")
    bar = fig.colorbar(cm.ScalarMappable(norm=norm, cmap=cmap), ax=list(axes), extend="both", shrink=0.8)
    bar.set_label("signed deviation, mm (+ = mesh outside CAD)")
    fig.suptitle(title)
    return save_figure(fig, path)


def histogram_png(path: str | Path, histograms: dict, *, title: str = "Share of surface per deviation band") -> Path:
    """PNG of one or more banded histograms ({label: Histogram}), shares in percent.

    The first histogram is drawn as bars, the others as step lines; under- and
    overflow are the outermost bars, labelled.
    """
    if not histograms:
        raise ValueError("no histograms to plot")
    fig = new_figure(1, 1.4)
    ax = fig.subplots()
    first = True
    for label, h in histograms.items():
        e = h.edges_mm
        w = e[1] - e[0]
        centres = np.concatenate([[e[0] - w / 2], 0.5 * (e[:-1] + e[1:]), [e[-1] + w / 2]])
        if first:
            ax.bar(centres[1:-1], 100 * h.shares[1:-1], width=0.9 * w, color="tab:blue", label=label)
            ax.bar(centres[[0, -1]], 100 * h.shares[[0, -1]], width=0.9 * w, color="0.5",
                   label=f"{label}: under/overflow")
            first = False
        else:
            ax.step(centres, 100 * h.shares, where="mid", label=label)
    e = next(iter(histograms.values())).edges_mm
    ax.set_xticks([e[0] - (e[1] - e[0]) / 2, 0.0, e[-1] + (e[1] - e[0]) / 2])
    ax.set_xticklabels([f"< {e[0]:g}", "0", f">= {e[-1]:g}"])
    ax.set_xlabel(f"signed deviation band ({e[1] - e[0]:g} mm wide), mm; + = mesh outside CAD")
    ax.set_ylabel("share of surface, %")
    ax.minorticks_on()
    ax.grid(alpha=0.3)
    ax.set_title(title)
    ax.legend()
    return save_figure(fig, path)


def zebra_png(
    path: str | Path,
    tess: Tessellation,
    frame: np.ndarray,
    *,
    stripes: int = 40,
    title: str = "Zebra (reflection lines)",
    height_px: int = 800,
) -> Path:
    """PNG of zebra stripes on the tessellated shape, anterior and posterior views."""
    rasters = render_tessellation_normals(tess, frame, VIEWS, height_px=height_px)
    r0 = rasters[0]
    aspect = (r0.extent_mm[1] - r0.extent_mm[0]) / (r0.extent_mm[3] - r0.extent_mm[2])
    fig = new_figure(2, aspect)
    axes = fig.subplots(1, 2)
    for ax, raster, name in zip(axes, rasters, VIEWS):
        ax.imshow(zebra_image(raster, stripes=stripes), extent=raster.extent_mm, interpolation="nearest")
        ax.set_title(name)
        ax.set_xlabel("mm")
    fig.suptitle(title)
    return save_figure(fig, path)


def shape_modes_png(
    path: str | Path,
    panels: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]],
    frame: np.ndarray,
    *,
    title: str,
    limit_mm: float,
    height_px: int = 700,
) -> Path:
    """PNG of shaded surfaces side by side (anterior view), one per (title, vertices, triangles, per-vertex
    signed offset from a reference, mm), coloured by the offset (red outward), on one scale in mm."""
    from matplotlib import cm, colormaps, colors

    norm = colors.Normalize(vmin=-limit_mm, vmax=limit_mm)
    cmap = colormaps["RdBu_r"]
    rasters = [render_mesh_values(v, f, d, frame, ("anterior",), height_px=height_px)[0] for _, v, f, d in panels]
    ext = np.array([r.extent_mm for r in rasters])
    aspect = (ext[:, 1] - ext[:, 0]).max() / (ext[:, 3] - ext[:, 2]).max()
    fig = new_figure(len(panels), aspect)
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, raster, (name, *_rest) in zip(axes, rasters, panels):
        rgb = cmap(norm(raster.values[..., 0]))[..., :3] * (0.45 + 0.55 * np.abs(raster.normal[..., 2]))[..., None]
        rgb[~raster.mask] = 1.0
        ax.imshow(rgb, extent=raster.extent_mm, interpolation="nearest")
        ax.set_xlim(ext[:, 0].min(), ext[:, 1].max())
        ax.set_ylim(ext[:, 2].min(), ext[:, 3].max())
        ax.set_title(name, fontsize=9)
        ax.set_xticks([])
    axes[0].set_ylabel("mm (proximal up)")
    bar = fig.colorbar(cm.ScalarMappable(norm=norm, cmap=cmap), ax=list(axes), extend="both", shrink=0.8)
    bar.set_label("offset from the mean along its normal, mm (+ = outward)")
    fig.suptitle(title)
    return save_figure(fig, path)
