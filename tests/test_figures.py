"""The figures' rasteriser (exact coverage, the front triangle), the colour maps' shared pixels, and panels
that show the images at their own pixels."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import ConvexHull, Delaunay

from bonecad.render.figures import (VIEWS, as_bytes, deviation_map_png, mesh_views, panel_figure, rasterise,
                                    render_mesh_values, screen_axes, to_screen)


def _polytope(seed: int = 0):
    """A convex polyhedron in general position (30 random points' hull), its triangles outward."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(30, 3)) * [12.0, 8.0, 20.0]
    hull = ConvexHull(points)
    used = np.unique(hull.simplices)
    vertices = points[used]
    faces = np.searchsorted(used, hull.simplices)
    centre = vertices.mean(axis=0)
    normal = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    inward = np.einsum("ij,ij->i", normal, vertices[faces[:, 0]] - centre) < 0
    faces[inward] = faces[inward][:, ::-1]
    return vertices, faces


@pytest.mark.parametrize("view", VIEWS)
def test_rasteriser_covers_exactly_the_pixel_centres_inside_the_projection(view):
    """A convex polyhedron covers the pixel centres inside its projected outline and no other (no pinhole,
    no overhang), so its area in pixels is the outline's within a pixel along its perimeter; each pixel shows
    a triangle facing the viewer (the front one), at the depth of the front surface."""
    vertices, faces = _polytope()
    frame = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))[0]
    axes = screen_axes(frame, view)
    pixel = 0.25
    s = to_screen(vertices, axes)
    bounds = (s[:, 0].min() - 1.0, s[:, 0].max() + 1.0, s[:, 1].min() - 1.0, s[:, 1].max() + 1.0)
    cover = rasterise(vertices, faces, axes, pixel_mm=pixel, bounds_mm=bounds)
    h, w = cover.shape
    left, _, _, top = cover.extent_mm
    rows, cols = np.divmod(np.arange(h * w), w)
    centres = np.column_stack([left + (cols + 0.5) * pixel, top - (rows + 0.5) * pixel])
    outline = ConvexHull(s[:, :2])
    # signed distance of each centre inside the outline (positive inside), mm
    inside_by = -(centres @ outline.equations[:, :2].T + outline.equations[:, 2]).max(axis=1)
    covered = np.zeros(h * w, dtype=bool)
    covered[cover.pixel] = True
    assert covered[inside_by > 1e-6].all()
    assert not covered[inside_by < -1e-6].any()
    area = outline.volume  # a 2-D hull's "volume" is its area
    assert abs(covered.sum() * pixel**2 - area) <= outline.area * pixel  # "area": the perimeter in 2-D
    normal = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    assert (normal[cover.triangle] @ axes[2] > 0).all()
    assert Delaunay(s[:, :2]).find_simplex(centres[cover.pixel]).min() >= 0
    on_plane = np.einsum("nk,nkj->nj", cover.barycentric, s[faces[cover.triangle]])
    np.testing.assert_allclose(on_plane[:, :2], centres[cover.pixel], atol=1e-9)
    np.testing.assert_allclose(on_plane[:, 2], cover.depth, atol=1e-9)


def test_colour_maps_share_the_mesh_pixels(tmp_path):
    """A colour map drawn on pixels computed once is the one rendered alone, byte for byte; the pixels hold
    no colour (a second model's values colour them afresh)."""
    vertices, faces = _polytope(2)
    frame = np.eye(3)
    pixels = mesh_views(vertices, faces, frame, VIEWS, height_px=120)
    for values in (vertices[:, 0] / 40.0, np.sin(vertices[:, 2] / 5.0) * 0.3):
        alone = deviation_map_png(tmp_path / "alone.png", vertices, faces, values, frame, height_px=120)
        shared = deviation_map_png(tmp_path / "shared.png", vertices, faces, values, frame, height_px=120,
                                   pixels=pixels)
        assert alone.read_bytes() == shared.read_bytes()
    with pytest.raises(ValueError, match="views"):
        render_mesh_values(vertices, faces, vertices[:, 0], frame, ("anterior",), height_px=120, pixels=pixels)


def test_panels_show_the_images_at_their_own_pixels():
    """The panel's axes are the image's pixels: drawn with interpolation "nearest", every pixel inside the
    frame is the image's own (no resampling, no blur)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    vertices, faces = _polytope(3)
    rasters = render_mesh_values(vertices, faces, vertices[:, 2], np.eye(3), ("anterior", "lateral"), height_px=150)
    fig, axes = panel_figure(rasters, 150)
    rng = np.random.default_rng(4)
    images = [rng.random((*r.mask.shape, 3)) for r in rasters]
    for ax, raster, image in zip(axes, rasters, images):
        ax.imshow(as_bytes(image), extent=raster.extent_mm, interpolation="nearest")
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    buffer = np.asarray(canvas.buffer_rgba())
    for ax, image in zip(axes, images):
        x0, y0, x1, y1 = np.round(ax.get_window_extent().extents).astype(int)
        shown = buffer[buffer.shape[0] - y1: buffer.shape[0] - y0, x0:x1, :3]
        assert shown.shape[:2] == image.shape[:2]
        # inside the frame (its line, 1.1 px wide, reaches into the second row of pixels)
        np.testing.assert_array_equal(shown[2:-2, 2:-2], as_bytes(image)[2:-2, 2:-2, :3])


def test_shape_modes_share_one_scale(tmp_path):
    """Panels of the shape modes are drawn on one pixel grid: a shape twice the size covers four times the
    pixels, and the figure is written."""
    from PIL import Image

    from bonecad.render.figures import shape_modes_png

    vertices, faces = _polytope(5)
    panels = [("small", vertices, faces, np.zeros(len(vertices))), ("large", 2 * vertices, faces, vertices[:, 2] / 20)]
    path = shape_modes_png(tmp_path / "modes.png", panels, np.eye(3), title="modes", limit_mm=1.0, height_px=300)
    image = np.asarray(Image.open(path).convert("RGB")).astype(int)
    assert image.shape[0] == 300 + 230
    frame = screen_axes(np.eye(3), "anterior")
    small, large = (ConvexHull(to_screen(v, frame)[:, :2]).volume for _, v, _, _ in panels)
    assert large == pytest.approx(4 * small)
    # the covered pixels inside the two panels (each as wide as the common bounds: panel_figure's layout,
    # 120 px left, 100 px between, 140 px a panel and 80 px of margins in all, 120 px for the bar)
    width = (image.shape[1] - 2 * 140 - 80 - 120) // 2
    covered = (image[125 + 2:425 - 2] < 250).any(axis=2)
    small_px, large_px = (covered[:, x + 2:x + width - 2].sum() for x in (120, 120 + width + 100))
    assert large_px / small_px == pytest.approx(4.0, rel=0.05)
