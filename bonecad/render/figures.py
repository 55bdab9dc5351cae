"""Offscreen images of surfaces: deviation colour maps and zebra stripes (no display needed).

Rendering is a numpy z-buffer rasteriser: each pixel shows the nearest triangle
whose orthographic projection contains the pixel's centre, with the centre's
barycentric coordinates on it (exact coverage: no random samples, no pinholes,
the same bytes for the same input). The pixels of a mesh's views
(:class:`Coverage`, :func:`mesh_views`) hold no colour, so the colour maps of
both models, which draw the same mesh, share them. No OpenGL, no VTK, so it runs
the same on a headless CI machine. Figures are composed with matplotlib's Agg
backend, each image on axes of exactly its pixels (copied, not resampled).

Views are anatomical: the caller passes ``frame``, a (3, 3) rotation whose
columns are the lateral (x), anterior (y) and proximal (z) unit axes in model
coordinates. Every view has proximal up: the anterior view looks from the front
(along -y), the posterior from the back (along +y), the lateral from the
lateral side (along -x), the medial from the medial side (along +x).

Zebra stripes (reflection lines): each pixel shows the reflection r of the view
direction about the exact surface normal; the stripe is
``floor(n_stripes * angle(r, stripe_axis) / pi) mod 2``, i.e. the reflection of
an environment of parallel light bands (Klass 1980, "Correction of local surface
irregularities using reflection lines", CAD 12(2), doi:10.1016/0010-4485(80)90021-5).
A position gap breaks a stripe, a tangent (G1) break makes stripes jump, a
curvature (G2) break makes them kink. Where the stripes get denser than the
pixels (tight curvature at the ends of the bone) each pixel shows the stripe
pattern averaged over its footprint (an analytic box filter of the square
wave), so they fade to grey instead of aliasing into noise.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from bonecad.staging import staged_file
from bonecad.analysis.statistics import Histogram
from bonecad.mesh.tessellation import Tessellation

View = Literal["anterior", "posterior", "medial", "lateral"]
VIEWS: tuple[View, ...] = ("anterior", "posterior", "medial", "lateral")
#: the direction towards the viewer of each view: (frame column, sign)
_TOWARD: dict[str, tuple[int, float]] = {"anterior": (1, 1.0), "posterior": (1, -1.0), "lateral": (0, 1.0),
                                         "medial": (0, -1.0)}


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
    if view not in _TOWARD:
        raise ValueError(f"view must be one of {VIEWS}, got {view!r}")
    column, sign = _TOWARD[view]
    toward, proximal = sign * f[:, column], f[:, 2]
    right = np.cross(proximal, toward)  # forward = -toward; right = forward x up
    return np.stack([right, proximal, toward])


def to_screen(points: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """(..., k) coordinates of (..., 3) points along the rows of ``axes`` (k, 3): einsum, 5-8x less CPU than
    ``points @ axes.T`` on millions of points (OpenBLAS threads on a (3, 3) product)."""
    return np.einsum("...j,kj->...k", points, axes)


@dataclass(frozen=True)
class Coverage:
    """Which triangle each pixel of one view shows: the pixel grid of a triangle mesh, before any colour.

    shape : (H, W) pixels; extent_mm : (left, right, bottom, top) of the pixel grid in screen mm
    pixel : (k,) flat indices of the covered pixels, ascending; triangle : (k,) the frontmost triangle
    at each one's centre; barycentric : (k, 3) the centre's coordinates on it; depth : (k,) mm, nearer = larger
    """

    shape: tuple[int, int]
    extent_mm: tuple[float, float, float, float]
    pixel: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray
    depth: np.ndarray

    def raster(self, normals: np.ndarray, values: np.ndarray) -> Raster:
        """The view with per-pixel ``normals`` (k, 3) in screen axes and ``values`` (k, m); empty pixels 0."""
        size = self.shape[0] * self.shape[1]
        mask = np.zeros(size, dtype=bool)
        mask[self.pixel] = True
        depth = np.full(size, -np.inf)
        depth[self.pixel] = self.depth
        vals = np.zeros((size, values.shape[1]))
        vals[self.pixel] = values
        nrm = np.zeros((size, 3))
        nrm[self.pixel] = normals
        h, w = self.shape
        return Raster(mask.reshape(h, w), depth.reshape(h, w), vals.reshape(h, w, -1), nrm.reshape(h, w, 3),
                      self.extent_mm)

    def interpolate(self, vertex_data: np.ndarray, triangles: np.ndarray, at: np.ndarray | slice = slice(None)
                    ) -> np.ndarray:
        """(k, m) per-vertex ``vertex_data`` (n, m) interpolated at the covered pixels' centres (``at``: some of
        them, indices into the k)."""
        corners = triangles[self.triangle[at]]
        return np.einsum("nk,nkj->nj", self.barycentric[at], vertex_data[corners])


def rasterise(vertices: np.ndarray, triangles: np.ndarray, axes: np.ndarray, *, pixel_mm: float,
              bounds_mm: tuple[float, float, float, float]) -> Coverage:
    """The frontmost triangle at each pixel centre of the orthographic view along ``axes`` (3, 3).

    Exact coverage, no random samples: every pixel centre inside a triangle's projection (edges
    included, within 1e-9 of a barycentric coordinate, so a shared edge leaves no pinhole) is a
    candidate, enumerated in the triangle's pixel bounding box without a Python loop; the nearest
    candidate per pixel wins (the lowest triangle index among exact ties: deterministic). Triangles
    seen edge-on cover nothing (their neighbours cover the same pixels).
    """
    left, _, _, top = bounds_mm
    width = int(np.ceil((bounds_mm[1] - left) / pixel_mm))
    height = int(np.ceil((top - bounds_mm[2]) / pixel_mm))
    s = to_screen(vertices, axes)
    x = (s[:, 0] - left) / pixel_mm - 0.5  # pixel units, the pixel centres at integers
    y = (top - s[:, 1]) / pixel_mm - 0.5
    corner = np.ascontiguousarray(triangles.T)  # one contiguous column per corner: no slow (m, 3) reductions
    x0, x1, x2 = x[corner]
    y0, y1, y2 = y[corner]
    c0 = np.maximum(np.ceil(np.minimum(np.minimum(x0, x1), x2)), 0).astype(np.int64)
    c1 = np.minimum(np.floor(np.maximum(np.maximum(x0, x1), x2)), width - 1).astype(np.int64)
    r0 = np.maximum(np.ceil(np.minimum(np.minimum(y0, y1), y2)), 0).astype(np.int64)
    r1 = np.minimum(np.floor(np.maximum(np.maximum(y0, y1), y2)), height - 1).astype(np.int64)
    e1x, e1y, e2x, e2y = x1 - x0, y1 - y0, x2 - x0, y2 - y0
    det = e1x * e2y - e1y * e2x
    nx = c1 - c0 + 1
    count = np.where((nx > 0) & (r1 >= r0) & (det != 0.0), nx * (r1 - r0 + 1), 0)
    live = np.flatnonzero(count)
    count = count[live]
    tri = np.repeat(live, count)  # one row per (triangle, pixel of its bounding box)
    row, col = np.divmod(np.arange(tri.size) - np.repeat(np.cumsum(count) - count, count), nx[tri])
    row += r0[tri]
    col += c0[tri]
    dx, dy = col - x0[tri], row - y0[tri]
    inv = 1.0 / det[tri]
    b1 = (dx * e2y[tri] - dy * e2x[tri]) * inv
    b2 = (e1x[tri] * dy - e1y[tri] * dx) * inv
    inside = np.flatnonzero((b1 >= -1e-9) & (b2 >= -1e-9) & (b1 + b2 <= 1.0 + 1e-9))
    tri, b1, b2 = tri[inside], b1[inside], b2[inside]
    pix = row[inside] * width + col[inside]
    z0, z1, z2 = s[:, 2][corner]
    z = z0[tri] + b1 * (z1 - z0)[tri] + b2 * (z2 - z0)[tri]
    bary = np.column_stack([1.0 - b1 - b2, b1, b2])
    # z-buffer: the nearest depth per pixel, then one candidate reaching it per pixel (the first)
    front = np.full(height * width, -np.inf)
    np.maximum.at(front, pix, z)
    reach = np.flatnonzero(z == front[pix])
    owner = np.full(height * width, len(z))
    np.minimum.at(owner, pix[reach], reach)
    first = owner[owner < len(z)]
    extent = (left, left + width * pixel_mm, top - height * pixel_mm, top)
    return Coverage((height, width), extent, pix[first], tri[first], bary[first], z[first])


def _view_bounds(vertices: np.ndarray, axes: np.ndarray, margin: float = 0.03):
    s = to_screen(vertices, axes)
    lo, hi = s[:, :2].min(axis=0), s[:, :2].max(axis=0)
    pad = margin * (hi - lo).max()
    return (lo[0] - pad, hi[0] + pad, lo[1] - pad, hi[1] + pad)


def mesh_views(vertices: np.ndarray, triangles: np.ndarray, frame: np.ndarray, views: tuple[View, ...] = VIEWS, *,
               height_px: int = 800) -> tuple[Coverage, ...]:
    """The pixels of a triangle mesh's ``views`` (:func:`rasterise`), the tallest ``height_px`` high: computed
    once, coloured by any per-vertex values (both models' colour maps draw the same mesh)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    frames = [screen_axes(frame, v) for v in views]
    bounds = [_view_bounds(vertices, a) for a in frames]
    pixel = min((b[3] - b[2]) / height_px for b in bounds)
    return tuple(rasterise(vertices, triangles, a, pixel_mm=pixel, bounds_mm=b) for a, b in zip(frames, bounds))


def render_mesh_values(
    vertices: np.ndarray,
    triangles: np.ndarray,
    vertex_values: np.ndarray,
    frame: np.ndarray,
    views: tuple[View, ...] = VIEWS,
    *,
    height_px: int = 800,
    pixels: tuple[Coverage, ...] | None = None,
) -> list[Raster]:
    """Views of a triangle mesh with per-vertex scalars interpolated (values[..., 0]) and shading normals;
    ``pixels``: the mesh's :func:`mesh_views` of the same ``views`` and ``height_px``, when the caller has them."""
    from bonecad.mesh.closest import vertex_normals

    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    vertex_values = np.asarray(vertex_values, dtype=np.float64)
    if vertex_values.shape != (len(vertices),):
        raise ValueError(f"vertex_values must be ({len(vertices)},), got {vertex_values.shape}")
    if pixels is None:
        pixels = mesh_views(vertices, triangles, frame, views, height_px=height_px)
    elif len(pixels) != len(views):
        raise ValueError(f"pixels of {len(pixels)} views for {len(views)} views")
    vn = vertex_normals(vertices, triangles)
    rasters = []
    for view, cover in zip(views, pixels):
        normals = to_screen(cover.interpolate(vn, triangles), screen_axes(frame, view))
        rasters.append(cover.raster(normals, cover.interpolate(vertex_values[:, None], triangles)))
    return rasters


def render_tessellation_normals(
    tess: Tessellation,
    frame: np.ndarray,
    views: tuple[View, ...] = VIEWS,
    *,
    height_px: int = 800,
) -> list[Raster]:
    """Views of a tessellated shape with exact surface normals at the pixel centres (for zebra).

    Each pixel centre's (u, v) is interpolated on the triangle it shows (the triangle lies within the
    chord error, 0.05 mm, of the surface) and the exact normal evaluated there, so stripe edges stay
    smooth across the triangles; a face without a spline surface keeps the interpolated node normals.
    values = (face index, u, v, triangle index).
    """
    sset = tess.packed_surfaces
    rasters = []
    for view, cover in zip(views, mesh_views(tess.vertices, tess.triangles, frame, views, height_px=height_px)):
        axes = screen_axes(frame, view)
        face = tess.triangle_face[cover.triangle]
        uv = cover.interpolate(tess.uv, tess.triangles)
        exact = np.flatnonzero(sset.group[face] >= 0)
        f = face[exact]
        lo_u, hi_u, lo_v, hi_v = sset.bounds[f].T
        uv[exact, 0] = np.clip(uv[exact, 0], lo_u, hi_u)
        uv[exact, 1] = np.clip(uv[exact, 1], lo_v, hi_v)
        sample = sset.evaluate(f, uv[exact, 0], uv[exact, 1], order=1)
        n = np.cross(sample.du, sample.dv)
        size = np.linalg.norm(n, axis=1, keepdims=True)
        good = size[:, 0] > 1e-12
        normals = np.zeros((len(face), 3))
        normals[exact[good]] = np.where(tess.reversed_faces[f[good]][:, None], -n[good], n[good]) / size[good]
        # the node normals, interpolated, where there is no surface or its normal vanishes (an apex)
        rest = np.ones(len(face), dtype=bool)
        rest[exact[good]] = False
        near = cover.interpolate(tess.normals, tess.triangles, np.flatnonzero(rest))
        normals[rest] = near / np.maximum(np.linalg.norm(near, axis=1, keepdims=True), 1e-300)
        values = np.column_stack([face.astype(float), uv, cover.triangle.astype(float)])
        rasters.append(cover.raster(to_screen(normals, axes), values))
    return rasters


def _square_wave_integral(phase: np.ndarray) -> np.ndarray:
    """Integral from 0 to ``phase`` of the light bands (1 where floor(phase) is odd, else 0)."""
    half = np.floor(phase / 2.0)
    return half + np.clip(phase - 2.0 * half - 1.0, 0.0, 1.0)


def _footprint(phase: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Change of ``phase`` across one pixel: per axis the smaller one-sided difference to a covered
    neighbour (a seam or silhouette on one side does not widen it), summed over both axes."""
    width = np.zeros_like(phase)
    for axis in (0, 1):
        steps = []
        for shift in (1, -1):
            other = np.roll(phase, shift, axis=axis)
            covered = np.roll(mask, shift, axis=axis)
            edge = [slice(None)] * 2
            edge[axis] = slice(0, 1) if shift == 1 else slice(-1, None)
            covered[tuple(edge)] = False  # no wrap-around
            steps.append(np.where(covered, np.abs(phase - other), np.inf))
        step = np.minimum(*steps)
        width += np.where(np.isfinite(step), step, 0.0)
    return width


def zebra_image(raster: Raster, *, stripes: int = 40, stripe_axis: str = "horizontal") -> np.ndarray:
    """(H, W, 3) RGB zebra image in [0, 1]; background white; stripes box-filtered over each pixel.

    ``stripe_axis``: 'horizontal' light bands run left-right (reflect about the
    screen up axis), 'vertical' run top-bottom.
    """
    mask = raster.mask
    rows, cols = np.nonzero(mask)  # the covered pixels only (about a third of the image)
    n = raster.normal[rows, cols]
    depth = raster.depth[rows, cols]
    # a perspective eye in front of the object (2x its height away), so the
    # reflections vary across flat regions too and stripes are dense
    left, right, bottom, top = raster.extent_mm
    h, w = mask.shape
    eye = np.array([(left + right) / 2, (bottom + top) / 2, depth.max(initial=0.0) + 2 * (top - bottom)])
    view = np.column_stack([left + (cols + 0.5) * (right - left) / w, top - (rows + 0.5) * (top - bottom) / h,
                            depth]) - eye
    view /= np.maximum(np.linalg.norm(view, axis=1, keepdims=True), 1e-300)
    r = view - 2.0 * np.einsum("nj,nj->n", n, view)[:, None] * n
    along = r[:, 1] if stripe_axis == "horizontal" else r[:, 0]
    phase = np.zeros(mask.shape)
    phase[rows, cols] = stripes * np.arccos(np.clip(along, -1.0, 1.0)) / np.pi
    # the mean of the band pattern over the pixel's footprint [phase - w/2, phase + w/2]
    width = np.maximum(_footprint(phase, mask)[rows, cols], 1e-6)
    centre = phase[rows, cols]
    light = (_square_wave_integral(centre + width / 2) - _square_wave_integral(centre - width / 2)) / width
    shade = 0.55 + 0.45 * np.abs(n[:, 2])
    img = np.ones((h, w, 3))
    img[rows, cols] = ((0.08 + 0.87 * light) * shade)[:, None]
    return img


def panel_figure(rasters: list[Raster], height_px: int, extra_width_px: int = 0):
    """A matplotlib Figure outside pyplot (Jupyter's inline plots keep working) with one panel per
    raster, side by side, each panel's axes exactly its image's pixels (``height_px`` tall), so an image
    drawn with interpolation "nearest" keeps its own pixels (no resampling filter to pay for or blur
    with); ``extra_width_px`` of room on the right (a colour bar)."""
    dpi = 100
    widths = [r.mask.shape[1] for r in rasters]
    left_px, gap_px, bottom_px = 120, 100, 105  # axis labels and ticks
    width_px = sum(widths) + 140 * len(rasters) + extra_width_px + 80  # 140 px a panel: the earlier sizes
    fig_height_px = height_px + 230
    fig = Figure(figsize=(width_px / dpi, fig_height_px / dpi), dpi=dpi)
    axes, x = [], left_px
    for raster, w in zip(rasters, widths):
        box = (x / width_px, bottom_px / fig_height_px, w / width_px, raster.mask.shape[0] / fig_height_px)
        axes.append(fig.add_axes(box))
        x += w + gap_px
    return fig, axes


def as_bytes(image: np.ndarray) -> np.ndarray:
    """(H, W, 4) uint8 RGBA, opaque, of an (H, W, 3) RGB image in [0, 1], truncated as matplotlib converts
    float images (the same colours); matplotlib copies such an image at 1:1 in a third of the time of a float one."""
    rgba = np.full((*image.shape[:2], 4), 255, dtype=np.uint8)
    rgba[..., :3] = np.clip(image, 0.0, 1.0) * 255
    return rgba


def save_figure(fig, path: str | Path, *, palette: bool = False) -> Path:
    """The figure as a PNG without alpha (the report embeds them): greyscale when it has no colour (a
    zebra figure: lossless, 2.5x smaller than matplotlib's RGBA), else RGB, or with ``palette`` 256
    colours (octree; no visible change on a shaded deviation map, 2.8x smaller: 1.6 to 0.57 MB; it
    would band a grey-shaded figure such as the curve plan)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from PIL import Image

    canvas = FigureCanvasAgg(fig)  # the pixels savefig would encode, without its PNG round trip
    canvas.draw()
    image = Image.fromarray(np.asarray(canvas.buffer_rgba())).convert("RGB")
    rgb = np.asarray(image)
    if (rgb[..., 0] == rgb[..., 1]).all() and (rgb[..., 1] == rgb[..., 2]).all():
        image = image.convert("L")
    elif palette:
        image = image.quantize(256, method=Image.Quantize.FASTOCTREE)
    path = Path(path)
    with staged_file(path) as tmp:
        image.save(tmp, format="png")
    return path


def _colour_panels(axes, rasters: list[Raster], views, images: list[np.ndarray]) -> None:
    for ax, raster, name, img in zip(axes, rasters, views, images):
        ax.imshow(as_bytes(img), extent=raster.extent_mm, interpolation="nearest")
        ax.set_title(name, y=1.0)  # (placed: matplotlib would measure the ticks for it, 0.1 s a figure)
        ax.set_xlabel("mm")
    axes[0].set_ylabel("mm (proximal up)")


def _shaded(raster: Raster, norm, cmap) -> np.ndarray:
    """(H, W, 3) RGB in [0, 1]: ``values[..., 0]`` through ``cmap`` after ``norm``, shaded by the normal's
    z (0.45 edge-on to 1 facing the viewer); white where nothing is drawn."""
    covered = raster.mask
    rgb = np.ones((*covered.shape, 3))
    shade = 0.45 + 0.55 * np.abs(raster.normal[covered, 2])
    rgb[covered] = cmap(norm(raster.values[covered, 0]))[:, :3] * shade[:, None]
    return rgb


def _colour_bar(fig, axes, norm, cmap, label: str, length: float) -> None:
    """A colour bar 100 px right of the last panel, 56 px wide, ``length`` of the panels' height: an axes
    of its own, not room taken from the panels (they keep their 1:1 pixels)."""
    from matplotlib import cm

    left, bottom, width, height = axes[-1].get_position().bounds
    fig_w = fig.get_figwidth() * fig.dpi
    cax = fig.add_axes((left + width + 100 / fig_w, bottom + (1 - length) / 2 * height, 56 / fig_w, length * height))
    fig.colorbar(cm.ScalarMappable(norm=norm, cmap=cmap), cax=cax, extend="both").set_label(label)


def deviation_map_png(
    path: str | Path,
    vertices: np.ndarray,
    triangles: np.ndarray,
    vertex_deviation_mm: np.ndarray,
    frame: np.ndarray,
    *,
    limit_mm: float | None = None,
    title: str = "Deviation (mesh - CAD), mm",
    height_px: int = 1600,
    pixels: tuple[Coverage, ...] | None = None,
) -> Path:
    """PNG of the mesh coloured by signed deviation from the four :data:`VIEWS`, ``height_px`` tall,
    with a colour bar in mm; ``pixels``: the mesh's :func:`mesh_views` (four views, ``height_px``), when
    the caller has them (both models' maps colour the same mesh).

    Diverging map (red = mesh outside the CAD model, blue = inside), symmetric
    about 0, clipped at ``limit_mm`` (default: the 99th percentile of
    |deviation| rounded up to 0.05 mm, at least 0.05 mm).
    """
    from matplotlib import colormaps, colors

    d = np.asarray(vertex_deviation_mm, dtype=np.float64)
    if limit_mm is None:
        limit_mm = max(0.05, np.ceil(np.percentile(np.abs(d), 99) / 0.05) * 0.05)
    rasters = render_mesh_values(vertices, triangles, d, frame, VIEWS, height_px=height_px, pixels=pixels)
    norm = colors.Normalize(vmin=-limit_mm, vmax=limit_mm)
    cmap = colormaps["RdBu_r"]
    fig, axes = panel_figure(rasters, height_px, extra_width_px=220)
    _colour_panels(axes, rasters, VIEWS, [_shaded(r, norm, cmap) for r in rasters])
    _colour_bar(fig, axes, norm, cmap, "signed deviation, mm (+ = mesh outside the CAD model)", 0.7)
    fig.suptitle(title)
    return save_figure(fig, path, palette=True)


def histograms_png(path: str | Path, models: dict[str, dict[str, Histogram]], *, tolerance_mm: float | None = None,
                   title: str = "Share of the surface per deviation band") -> Path:
    """PNG of the models' banded deviation histograms overlaid, one column per region: the shares in
    percent on a linear axis (the peak) above a logarithmic one (the tails against the tolerance).

    ``models``: model name -> region name -> Histogram (the same regions and
    bands in every model); under- and overflow as the outermost bands,
    labelled; dashed lines at +-``tolerance_mm``.
    """
    if not models or not all(models.values()):
        raise ValueError("no histograms to plot")
    regions = list(next(iter(models.values())))
    fig = Figure(figsize=(4.2 * len(regions) + 1.0, 8.0), dpi=100)
    grid = fig.subplots(2, len(regions), sharey="row", sharex=True, squeeze=False)
    for ax, region in [*zip(grid[0], regions), *zip(grid[1], regions)]:
        for (name, hists), colour in zip(models.items(), ("tab:blue", "tab:orange", "tab:green")):
            h = hists[region]
            e = h.edges_mm
            w = e[1] - e[0]
            centres = np.concatenate([[e[0] - w / 2], 0.5 * (e[:-1] + e[1:]), [e[-1] + w / 2]])
            ax.step(centres, 100 * h.shares, where="mid", color=colour, label=name)
            ax.fill_between(centres, 100 * h.shares, step="mid", color=colour, alpha=0.15)
        if tolerance_mm is not None:
            for x in (-tolerance_mm, tolerance_mm):
                ax.axvline(x, color="k", ls="--", lw=1.0)
        ax.set_xticks([e[0] - w / 2, e[0] / 2, 0.0, e[-1] / 2, e[-1] + w / 2])
        ax.set_xticklabels([f"< {e[0]:g}", f"{e[0] / 2:g}", "0", f"{e[-1] / 2:g}", f">= {e[-1]:g}"])
        ax.grid(alpha=0.3)
    for ax, region in zip(grid[0], regions):
        ax.set_title(region, y=1.0)
    for ax in grid[1]:
        ax.set_yscale("log")
        ax.set_ylim(bottom=0.01)
        ax.set_xlabel(f"signed deviation, mm ({w:g} mm bands)")
    grid[0, 0].set_ylabel("share of surface, %")
    grid[1, 0].set_ylabel("share of surface, % (log)")
    handles, labels = grid[0, 0].get_legend_handles_labels()
    if tolerance_mm is not None:
        handles.append(Line2D([], [], color="k", ls="--"))
        labels.append(f"tolerance +-{tolerance_mm:g} mm")
    grid[0, 0].legend(handles, labels, loc="upper left", fontsize=9)
    fig.suptitle(title + " (+ = mesh outside the CAD model)")
    # fixed margins in inches (what tight_layout found for this grid, which cost 0.23 of the 1.0 s CPU of the figure)
    width, height = fig.get_size_inches()
    fig.subplots_adjust(left=0.75 / width, right=1.0 - 0.1 / width, bottom=0.55 / height, top=1.0 - 0.75 / height,
                        wspace=0.08, hspace=0.1)
    return save_figure(fig, path)


def zebra_png(
    path: str | Path,
    tess: Tessellation,
    frame: np.ndarray,
    *,
    stripes: int = 40,
    title: str = "Zebra (reflection lines)",
    height_px: int = 1600,
) -> Path:
    """PNG of zebra stripes on the tessellated shape from the four :data:`VIEWS`, ``height_px`` tall."""
    rasters = render_tessellation_normals(tess, frame, VIEWS, height_px=height_px)
    fig, axes = panel_figure(rasters, height_px)
    _colour_panels(axes, rasters, VIEWS, [zebra_image(r, stripes=stripes) for r in rasters])
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
    signed offset from a reference, mm), coloured by the offset (red outward), on one scale in mm: every
    panel on the pixel grid of their common bounds, ``height_px`` tall."""
    from matplotlib import colormaps, colors

    norm = colors.Normalize(vmin=-limit_mm, vmax=limit_mm)
    cmap = colormaps["RdBu_r"]
    axes_mm = screen_axes(frame, "anterior")
    bounds = np.array([_view_bounds(np.asarray(v, dtype=np.float64), axes_mm) for _, v, _, _ in panels])
    common = (bounds[:, 0].min(), bounds[:, 1].max(), bounds[:, 2].min(), bounds[:, 3].max())
    pixel = (common[3] - common[2]) / height_px
    rasters = []
    for _, v, f, d in panels:
        v, f = np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)
        cover = rasterise(v, f, axes_mm, pixel_mm=pixel, bounds_mm=common)
        rasters.append(render_mesh_values(v, f, d, frame, ("anterior",), pixels=(cover,))[0])
    fig, axes = panel_figure(rasters, height_px, extra_width_px=120)
    for ax, raster, (name, *_rest) in zip(axes, rasters, panels):
        ax.imshow(as_bytes(_shaded(raster, norm, cmap)), extent=raster.extent_mm, interpolation="nearest")
        ax.set_title(name, fontsize=9, y=1.0)
        ax.set_xticks([])
    axes[0].set_ylabel("mm (proximal up)")
    _colour_bar(fig, axes, norm, cmap, "offset from the mean along its normal, mm (+ = outward)", 0.8)
    fig.suptitle(title)
    return save_figure(fig, path, palette=True)
