"""report.json / report.html and the golden-histogram regression mechanism.

Goldens are updated on purpose with ``BONECAD_UPDATE_GOLDENS=1 pytest tests/test_analysis_report.py``.
"""
from __future__ import annotations

import json
import re
from html.parser import HTMLParser

import numpy as np
import pytest

from bonecad.analysis.continuity import knot_continuity, seam_continuity
from bonecad.analysis.deviation import shape_deviation
from tests.goldens import UPDATE_ENV, GoldenMismatch, assert_histogram_matches, compare_histogram
from bonecad.render.figures import deviation_map_png, histograms_png
from bonecad.analysis.model import ModelReport
from bonecad.export.registry import export
from bonecad.export.report import SCHEMA, AT_NOISE, MET, NOT_MET, ReportDocument, Tolerances, verdict
from bonecad.analysis.statistics import Histogram
from bonecad.occ.brepmesh import brepmesh_face
from bonecad.occ.read_faces import face_spline_surface
from bonecad.occ.tessellate import tessellate
from bonecad.errors import InputError
from tests.defaults import TESSELLATION, CONTINUITY, BANDS_MM
from dataclasses import replace


RADIUS = 10.0
GOLDEN = "sphere_r10_wavy"


@pytest.fixture(scope="module")
def sphere():
    from OCP.BRepBuilderAPI import BRepBuilderAPI_NurbsConvert
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeSphere

    shape = BRepBuilderAPI_NurbsConvert(BRepPrimAPI_MakeSphere(RADIUS).Shape(), True).Shape()
    return shape, tessellate(shape, TESSELLATION)


def wavy_mesh(tess, amplitude_mm: float, offset_mm: float = 0.0):
    """The sphere's tessellation with a radial wave of known amplitude (a stand-in 'bone mesh')."""
    # the mesh the golden was recorded with: BRepMesh at 0.05 mm, edges bisected to 1 mm
    # (fixed here, so the golden does not move with the analysis' own tessellator)
    face = tess.faces[0]
    surface, native = face_spline_surface(face)
    settings = replace(TESSELLATION, deflection_mm=0.05, angular_deflection_rad=0.2, coverage_tolerance=0.005,
                                    area_rel_eps=1e-6, max_edge_mm=1.0)
    v, _, triangles, _ = brepmesh_face(face, 0, surface, native, False, settings)
    unit = v / np.linalg.norm(v, axis=1, keepdims=True)
    wave = amplitude_mm * np.sin(3 * np.arctan2(unit[:, 1], unit[:, 0])) * np.cos(2 * np.arcsin(unit[:, 2]))
    return v + unit * (wave + offset_mm)[:, None], triangles


def _regions(points):
    return np.where(points[:, 2] < -5, "distal", np.where(points[:, 2] > 5, "proximal", "shaft"))


def _deviation(sphere, offset_mm=0.0):
    shape, tess = sphere
    v, f = wavy_mesh(tess, 0.3, offset_mm)
    return v, f, shape_deviation(v, f, tess, edges_mm=BANDS_MM, sample_points=20000, regions=_regions)


def test_golden_histogram_passes_on_the_model_and_catches_a_perturbed_one(sphere):
    """Stored golden data/goldens/sphere_r10_wavy.json (rewritten when BONECAD_UPDATE_GOLDENS=1)."""
    _, _, good = _deviation(sphere)
    result = assert_histogram_matches(good.mesh_to_cad.histogram, GOLDEN, tolerance=0.01,
                                      note="NURBS sphere r=10 vs its 0.05 mm tessellation with a 0.3 mm wave")
    assert result.ok
    # the model moved 0.05 mm outwards: bands shift by half a band
    _, _, moved = _deviation(sphere, offset_mm=0.05)
    with pytest.raises(GoldenMismatch, match="percentage points"):
        assert_histogram_matches(moved.mesh_to_cad.histogram, GOLDEN, tolerance=0.01, update=False)


def test_golden_update_mode_and_missing_golden(tmp_path, monkeypatch):
    hist = Histogram(np.array([-1.0, 0.0, 1.0]), np.array([0.1, 0.4, 0.4, 0.1]))
    monkeypatch.delenv(UPDATE_ENV, raising=False)
    with pytest.raises(InputError, match=UPDATE_ENV):
        compare_histogram(hist, "new", golden_dir=tmp_path)
    monkeypatch.setenv(UPDATE_ENV, "1")
    assert compare_histogram(hist, "new", golden_dir=tmp_path).updated
    monkeypatch.delenv(UPDATE_ENV)
    assert compare_histogram(hist, "new", golden_dir=tmp_path).worst == 0.0
    shifted = Histogram(hist.edges_mm, np.array([0.1, 0.38, 0.42, 0.1]))
    assert compare_histogram(shifted, "new", golden_dir=tmp_path, tolerance=0.03).ok
    with pytest.raises(GoldenMismatch, match=r"\[0, 1\)"):
        assert_histogram_matches(shifted, "new", golden_dir=tmp_path, tolerance=0.01)
    other_bands = Histogram(np.array([-2.0, 0.0, 2.0]), hist.shares)
    with pytest.raises(GoldenMismatch, match="other bands"):
        compare_histogram(other_bands, "new", golden_dir=tmp_path)


def test_report_json_and_html(sphere, tmp_path):
    shape, tess = sphere
    v, f, dev = _deviation(sphere)
    # the wave, measured on the tessellation: within its chord error of the exact distance
    assert np.abs(dev.vertex_deviation_mm).max() <= 0.3 + tess.chord_error_mm.max() + 1e-6
    frame = np.eye(3)
    cmap = deviation_map_png(tmp_path / "deviation_nurbs.png", v, f, dev.vertex_deviation_mm, frame, height_px=200)
    hist = histograms_png(tmp_path / "histogram_nurbs.png",
                          {"nurbs": {"overall": dev.mesh_to_cad.histogram, **dev.mesh_to_cad.region_histograms}},
                          tolerance_mm=0.25)
    models = [
        ModelReport("nurbs", {"faces": 1, "control_points": 45}, dev, seam_continuity(shape, tolerances=CONTINUITY),
                    knot_continuity(shape), {"deviation map": cmap, "histogram": hist}),
        ModelReport("tspline", {"faces": 1, "control_points": 30, "cap_control_points": 4}, dev,
                    seam_continuity(shape, tolerances=CONTINUITY), None, {}),
    ]
    files = export("report", ReportDocument(input_summary={"file": "sphere", "triangles": len(f)},
                                            frame={"axes": frame},
                                            models=tuple(models), timings_s=dict(dev.timings_s)), tmp_path)
    json_path, html_path = files["json"], files["html"]
    report = json.loads(json_path.read_text())
    assert report["schema"] == SCHEMA
    stats = report["models"]["nurbs"]["deviation"]["mesh_to_cad"]["stats"]
    assert stats["rms_mm"] == pytest.approx(dev.mesh_to_cad.stats.rms_mm)
    assert set(report["models"]["nurbs"]["deviation"]["mesh_to_cad"]["regions"]) == {"distal", "shaft", "proximal"}
    assert report["models"]["nurbs"]["figures"] == {"deviation map": "deviation_nurbs.png",
                                                    "histogram": "histogram_nurbs.png"}
    rows = {r["quantity"]: r for r in report["comparison"]}
    counts = rows["control points (all faces, apex caps included)"]
    assert counts["nurbs"] == 45 and counts["tspline"] == 34
    within = rows["surface within 0.25 mm"]["nurbs"]
    d = dev.mesh_to_cad
    assert within == pytest.approx(d.weights[np.abs(d.deviation_mm) <= 0.25].sum() / d.weights.sum())
    text = html_path.read_text()
    assert "NURBS versus T-spline" in text
    assert text.count("data:image/png;base64,") == 2


def test_report_without_both_models_has_no_comparison(tmp_path):
    files = export("report", ReportDocument(input_summary={}, frame={}, models=(ModelReport("nurbs"),), timings_s={}),
                   tmp_path)
    json_path, html_path = files["json"], files["html"]
    assert json.loads(json_path.read_text())["comparison"] is None
    assert "NURBS versus T-spline" not in html_path.read_text()
    with pytest.raises(FileNotFoundError, match="missing"):
        export("report", ReportDocument(input_summary={}, frame={},
                                        models=(ModelReport("nurbs", figures={"x": tmp_path / "no.png"}),),
                                        timings_s={}),
               tmp_path)


class Cells(HTMLParser):
    """The text of every table cell, and the verdict badges, of an HTML page."""

    def __init__(self):
        super().__init__()
        self.cells: list[str] = []
        self.verdicts: dict[str, str] = {}
        self._in_cell = False
        self._card = ""

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag in ("td", "th"):
            self._in_cell = True
            self.cells.append("")
        if (attrs.get("id") or "").startswith("card-"):
            self._card = attrs["id"][5:]
        if "data-verdict" in attrs:
            self.verdicts[self._card] = attrs["data-verdict"]

    def handle_endtag(self, tag):
        if tag in ("td", "th"):
            self._in_cell = False

    def handle_data(self, data):
        if self._in_cell:
            self.cells[-1] += data


def parse_cells(text: str) -> Cells:
    parser = Cells()
    parser.feed(text)
    return parser


def test_summary_first_with_verdicts_and_no_raw_lists_in_cells(sphere, tmp_path):
    """The summary cards say met / not met / stopped at the data's noise (with the reason) against the run's
    tolerances, measured on the deviation; no table cell holds a Python list or dict."""
    shape, tess = sphere
    v, f, dev = _deviation(sphere)
    d = dev.mesh_to_cad
    worst = max(d.stats.max_outside_mm, d.stats.max_inside_mm)
    loose = Tolerances(share=0.5, within_mm=0.3, max_deviation_mm=worst + 0.01, rms_mm=d.stats.rms_mm + 0.01)
    tight = replace(loose, max_deviation_mm=worst / 2)
    noise = "tolerances met up to the data's noise: 0.40% of the surface lies beyond 0.25 mm"
    assert verdict(ModelReport("nurbs", {}, dev), loose)["verdict"] == MET
    missed = verdict(ModelReport("nurbs", {}, dev), tight)
    assert missed["verdict"] == NOT_MET and "largest deviation" in missed["reason"]
    stopped = verdict(ModelReport("tspline", {"fit_stopped": noise}, dev), tight)
    assert stopped["verdict"] == AT_NOISE and noise in stopped["reason"]
    (tmp_path / "nurbs.step").write_bytes(b"x" * 2048)
    models = (ModelReport("nurbs", {"faces": 1, "control_points": 45, "surfaces": [{"knots_u": [0.0, 0.5, 1.0, 1.0],
                                                                                     "degrees": [3, 3]}]},
                          dev, seam_continuity(shape, tolerances=CONTINUITY), knot_continuity(shape)),
              ModelReport("tspline", {"faces": 1, "control_points": 30, "fit_stopped": noise,
                                      "fit": {"rms_mm": 0.1}, "fit_history": [{"rms_mm": 0.2}]}, dev))
    doc = ReportDocument(input_summary={"file": "sphere.stl", "triangles": len(f), "side": "right",
                                        "bodies": [{"role": "tibia", "triangles": len(f)},
                                                   {"role": "fibula", "triangles": 10}],
                                        "repairs": ["merged duplicate vertices"]},
                         frame={"bone_frame": {"origin": [1.0, 2.0, 3.0], "lateral": [1.0, 0.0, 0.0]},
                                "regions_mm_above_origin": {"shaft": [30.0, 280.0]}, "axes": np.eye(3)},
                         models=models, timings_s={"deviation": 1.5}, tolerances=tight)
    files = export("report", doc, tmp_path)
    report = json.loads(files["json"].read_text())
    assert report["summary"]["nurbs"]["verdict"] == NOT_MET
    assert report["summary"]["nurbs"]["files_bytes"] == {"nurbs.step": 2048}
    assert report["summary"]["tspline"]["verdict"] == AT_NOISE
    assert report["summary"]["nurbs"]["within_mm"]["0.25"] == pytest.approx(d.share_within(0.25))
    text = files["html"].read_text()
    page = parse_cells(text)
    assert page.verdicts == {"nurbs": NOT_MET, "tspline": AT_NOISE}
    assert text.index("Summary") < text.index("Model: nurbs")
    assert len(page.cells) > 100
    raw = [c for c in page.cells if c.lstrip().startswith(("[", "{", "(")) or "': " in c]
    assert not raw, raw[:5]
    assert "fibula" in page.cells and "merged duplicate vertices" in text


def test_3d_view_is_offline_decimated_and_signed():
    """The view's meshes keep the triangle budget; a model 1 mm outside the mesh reads -1 mm (mesh inside the
    CAD model); the fragment inlines three.js and fetches nothing."""
    import trimesh

    from bonecad.export.viewer import decimate, deviation_at, input_view, model_view, viewer_html
    from bonecad.mesh.closest import TriangleLocator

    bone = trimesh.creation.icosphere(subdivisions=5, radius=10.0)
    tree = TriangleLocator(bone.vertices, bone.faces)
    v, f = decimate(bone.vertices, bone.faces, 2000)
    assert 1500 <= len(f) <= 2000
    outer = trimesh.creation.icosphere(subdivisions=3, radius=11.0)
    assert deviation_at(outer.vertices, tree) == pytest.approx(-1.0, abs=0.02)
    halves = (outer.triangles_center[:, 2] > 0).astype(int)  # two "faces": the seam is the equator
    model = model_view("tspline", outer.vertices, outer.faces, halves, tree, 500)
    assert len(model.seams) > 10 and np.abs(model.seams[..., 2]).max() < 2.0  # within a triangle of z = 0
    mesh = input_view(bone.vertices, bone.faces, {"tspline": np.full(len(bone.vertices), 0.5)}, 3000)
    assert len(model.triangles) <= 500 and np.allclose(mesh.deviation_mm["tspline"], 0.5)
    page = viewer_html([mesh, model], {"bone_frame": {"origin": [0, 0, 0], "lateral": [1, 0, 0],
                                                      "anterior": [0, 1, 0], "proximal": [0, 0, 1]}})
    assert "TrackballControls" in page and "view-canvas" in page
    assert not re.search(r"<(script|link|img|iframe)[^>]+(src|href)=", page)  # nothing fetched: all inlined


def test_result_show_gives_the_3d_view_in_jupyter(phantom, phantom_frame):
    """``Reconstruction.show()``: the report's 3-D view as an HTML object Jupyter displays (an iframe)."""
    import trimesh

    from bonecad.export.viewer import input_view
    from bonecad.run.pipeline import Reconstruction

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    view = input_view(sphere.vertices, sphere.faces, {"tspline": np.zeros(len(sphere.vertices))}, 500)
    shown = Reconstruction(bone=phantom, frame=phantom_frame, views=(view,)).show()
    assert shown.data.startswith("<iframe srcdoc=") and "TrackballControls" in shown.data
    assert "view-canvas" in shown.data and "&lt;script" in shown.data
