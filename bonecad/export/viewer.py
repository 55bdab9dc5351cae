"""The report's interactive 3-D view: offline, self-contained HTML (three.js inlined, no network).

The meshes (the input mesh and each model's tessellation, decimated to
``[analysis] view_max_triangles`` by the working copy's quadric edge collapse)
are embedded as base64 float32/uint32 arrays with their signed deviation per vertex (mm, positive = mesh outside the CAD
model), and each model's seams (the borders of its faces, from the full
tessellation) as line segments. The page colours them on a diverging scale
(blue inside, red outside, symmetric about 0, the limit editable) or shows
reflection lines (zebra, computed per pixel in a shader from the interpolated
normals of the decimated mesh: smoothed, so the report's zebra figures, on the
exact normals, are the check of the seams), lays them side by side as seen
from the front, draws the anatomical frame's axes and the region boundaries
as planes across each bone, and orbits/zooms with the mouse (three.js
TrackballControls); checkboxes show or hide each mesh, the seams, the planes
and the axes.

three.js (r140, MIT) is the copy trimesh bundles for its notebook viewer.
"""
from __future__ import annotations

import base64
import html
import json
import zipfile
from dataclasses import dataclass, field

import numpy as np

from bonecad.mesh.closest import TriangleLocator
from bonecad.mesh.topology import edge_counts, merge_close_vertices
from bonecad.mesh.working import simplified


@dataclass(frozen=True)
class ViewMesh:
    """One mesh of the 3-D view: vertices (n, 3) mm, triangles (m, 3), and per vertex the signed
    deviation of each named comparison (mm, positive = mesh outside the CAD model)."""

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    deviation_mm: dict[str, np.ndarray]
    seams: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))  # (k, 2, 3) segment ends, mm


def decimate(vertices: np.ndarray, triangles: np.ndarray, max_triangles: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertices within 1e-6 of the bounding box's diagonal merged (a tessellation's face borders), then
    quadric edge-collapse decimation to at most about ``max_triangles`` triangles (the working copy's
    simplifier, ``mesh.working.simplified``); deterministic."""
    radius = 1e-6 * float(np.linalg.norm(np.ptp(np.asarray(vertices, dtype=np.float64), axis=0)))
    points, faces = merge_close_vertices(vertices, triangles, radius)
    if len(faces) > max_triangles:
        return simplified(points, faces, int(max_triangles))
    return points, faces


def deviation_at(points: np.ndarray, bone: TriangleLocator) -> np.ndarray:
    """(N,) signed deviation (mm) at points of a CAD model's surface: their distance to the bone mesh
    (``bone``: its closest-point tree, with its vertex normals), positive where the mesh lies outside the
    model (the sign convention of ``analysis.deviation``)."""
    near = bone.query(points)
    normal = np.einsum("nk,nkj->nj", near.barycentric, bone.vertex_normals[bone.triangles[near.triangle]])
    outside = np.einsum("ij,ij->i", points - near.points, normal) > 0
    return np.where(outside, -near.distance, near.distance)


def face_seams(vertices: np.ndarray, triangles: np.ndarray, triangle_face: np.ndarray) -> np.ndarray:
    """(k, 2, 3) the edges of a tessellation where two faces meet or the surface ends (mm): the edges
    of one triangle only (faces tessellated apart) or of two triangles on different faces."""
    triangles = np.asarray(triangles, dtype=np.int64)
    edges = edge_counts(triangles, len(vertices))
    face = np.asarray(triangle_face)[edges.half_edges // 3]
    seam = (edges.faces_per_edge == 1) | (face[:, 0] != face[:, 1])
    low = edges.keys[seam] // len(vertices)
    high = edges.keys[seam] % len(vertices)
    return np.stack([vertices[low], vertices[high]], axis=1)


def model_view(name: str, vertices: np.ndarray, triangles: np.ndarray, triangle_face: np.ndarray,
               bone: TriangleLocator, max_triangles: int) -> ViewMesh:
    """A model's tessellation (``triangle_face``: each triangle's face), decimated, coloured by its
    deviation from the bone mesh (``bone``: its closest-point tree), with its seams."""
    v, f = decimate(vertices, triangles, max_triangles)
    return ViewMesh(name, v, f, {name: deviation_at(v, bone)}, face_seams(vertices, triangles, triangle_face))


def input_view(bone_vertices: np.ndarray, bone_faces: np.ndarray, vertex_deviation_mm: dict[str, np.ndarray],
               max_triangles: int) -> ViewMesh:
    """The input mesh, decimated; each model's vertex deviation carried over from the nearest original
    vertex (``vertex_deviation_mm``: model name -> (n,) mm at the bone's vertices)."""
    from scipy.spatial import cKDTree

    v, f = decimate(bone_vertices, bone_faces, max_triangles)
    _, nearest = cKDTree(bone_vertices).query(v)
    return ViewMesh("input mesh", v, f, {k: np.asarray(d)[nearest] for k, d in vertex_deviation_mm.items()})


def three_js() -> str:
    """three.js r140 with TrackballControls: the script trimesh bundles for its notebook viewer, read from
    trimesh's package data without importing trimesh (0.7 s at the end of every run)."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.find_spec("trimesh")
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError("trimesh is not installed: the 3-D view needs the three.js it bundles")
    bundle = Path(next(iter(spec.submodule_search_locations))) / "resources" / "templates" / "viewer.zip"
    with zipfile.ZipFile(bundle) as archive:
        template = archive.read("viewer.html.template").decode("utf-8")
    start = template.index("<script>") + len("<script>")
    end = template.index("var camera,controls,scene")  # trimesh's own viewer code follows
    return template[start:end]


def _viewer_js() -> str:
    """The view's own script (``data/viewer.js``)."""
    from importlib import resources

    return resources.files("bonecad").joinpath("data/viewer.js").read_text()


def _b64(array: np.ndarray, dtype) -> str:
    return base64.b64encode(np.ascontiguousarray(array, dtype=dtype).tobytes()).decode("ascii")


def scene_json(meshes: list[ViewMesh], frame: dict, limit_mm: float) -> str:
    """The view's data as JSON: meshes (base64 arrays), the frame's origin and axes, the region boundaries'
    heights above the origin (mm), the colour limit."""
    bone = frame.get("bone_frame", {})
    regions = frame.get("regions_mm_above_origin", {})
    data = {
        "limit_mm": limit_mm,
        "frame": {k: bone.get(k) for k in ("origin", "lateral", "anterior", "proximal")} if bone else None,
        "boundaries_mm": [regions["shaft"][0], regions["shaft"][1]] if "shaft" in regions else [],
        "meshes": [{"name": m.name, "positions": _b64(m.vertices, "<f4"), "indices": _b64(m.triangles, "<u4"),
                    "seams": _b64(m.seams, "<f4"),
                    "deviation": {k: _b64(d, "<f4") for k, d in m.deviation_mm.items()}} for m in meshes],
    }
    return json.dumps(data)


def colour_limit_mm(meshes: list[ViewMesh]) -> float:
    """The colour scale's limit: the 99th percentile of |deviation| over all meshes, up to 0.05 mm steps."""
    values = np.concatenate([np.abs(d) for m in meshes for d in m.deviation_mm.values()] or [np.zeros(1)])
    return float(max(0.05, np.ceil(np.percentile(values, 99) / 0.05) * 0.05))


def viewer_html(meshes: list[ViewMesh], frame: dict) -> str:
    """The 3-D view as an HTML fragment (a canvas, controls, three.js and the data inlined)."""
    if not meshes:
        return ""
    toggles = "".join(
        f"<label style='margin-right:1.2em'><input type='checkbox' checked data-mesh='{i}'> "
        f"{html.escape(m.name)}</label>"
        for i, m in enumerate(meshes))
    choices = list(dict.fromkeys(k for m in meshes for k in m.deviation_mm))
    colour_by = "".join(f"<option value='{html.escape(k)}'{' selected' if k == choices[-1] else ''}>"
                        f"{html.escape(k)}</option>" for k in choices)
    return (
        "<div id='viewer3d'>"
        "<p>Left to right, seen from the front: " + ", ".join(html.escape(m.name) for m in meshes)
        + ". Drag to orbit, wheel to zoom, right-drag to pan. Colour: signed deviation, mm "
        "(red = mesh outside the CAD model, blue = inside); the input mesh is coloured by its deviation from "
        f"the model chosen here: <select id='colour-by'>{colour_by}</select></p>"
        f"<p>{toggles}</p><p><label style='margin-right:1.2em'>show <select id='shading'>"
        "<option value='deviation' selected>deviation</option><option value='zebra'>zebra (reflection lines)"
        "</option><option value='plain'>plain</option></select></label>"
        "<label style='margin-right:1.2em'>colour limit, mm "
        "<input id='colour-limit' type='number' step='0.05' min='0.01' style='width:5em'></label>"
        "<label style='margin-right:1.2em'>stripes <input id='stripes' type='number' step='5' min='5' "
        "value='40' style='width:4em'></label>"
        "<label style='margin-right:1.2em'><input type='checkbox' id='show-seams'> seams (face borders)"
        "</label><label style='margin-right:1.2em'><input type='checkbox' id='show-planes' checked> region "
        "boundaries</label><label><input type='checkbox' id='show-frame' checked> frame axes</label></p>"
        "<div style='position:relative'><canvas id='view-canvas' width='1200' height='700' "
        "style='width:100%;max-width:1200px;border:1px solid #999;background:#fff'></canvas>"
        "<div id='colour-scale' style='display:flex;align-items:center;gap:6px;margin-top:4px'>"
        "<span id='scale-lo'></span><span style='display:inline-block;width:300px;height:14px;"
        "background:linear-gradient(to right,rgb(33,102,172),rgb(247,247,247),rgb(178,24,43))'></span>"
        "<span id='scale-hi'></span><span>mm</span></div></div>"
        f"<script>{three_js()}</script>"
        f"<script id='view-data' type='application/json'>{scene_json(meshes, frame, colour_limit_mm(meshes))}"
        f"</script><script>{_viewer_js()}</script></div>"
    )
