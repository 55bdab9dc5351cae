"""JSON exporters: frame.json, curves.json, tspline.json and patch.json (scanner coordinates, mm).

No timings go into them (report.json has those): the same input gives the same files.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bonecad.anatomy.frame import AnatomicalFrame
from bonecad.contours.curves import ContourSet
from bonecad.export.registry import exporter
from bonecad.splines.surface import BSplineSurface
from bonecad.splines.tspline import to_dict
from bonecad.staging import staged_file
from bonecad.tspline_model.model import TSplineModel, to_scanner
from bonecad.tspline_model.patch import Footprint


@dataclass(frozen=True)
class FrameDocument:
    """What frame.json holds: the input's summary (``BoneMesh.summary()``) and the anatomical frame."""

    input_summary: dict[str, Any]
    frame: AnatomicalFrame


def write_json(data: dict, path: Path, *, indent: int | None = 2) -> Path:
    """``data`` as JSON at ``path``, written atomically."""
    with staged_file(path) as tmp:
        tmp.write_text(json.dumps(data, indent=indent) + ("\n" if indent is not None else ""))
    return path


@exporter("frame", "json")
def frame_json(doc: FrameDocument, out_dir: Path) -> Path:
    return write_json({"input": doc.input_summary, **doc.frame.as_dict()}, out_dir / "frame.json")


def contours_dict(contours: ContourSet) -> dict:
    """curves.json: per curve its poles and knots (scanner mm), achieved deviation, tolerance, repairs."""
    frame = contours.frame
    curves = []
    for c in contours.all_curves():
        scanner = c.curve.transformed(frame.axes, frame.origin)
        curves.append({
            "name": c.name,
            "region": c.region,
            "index": c.index,
            "angle_deg": c.angle_deg,
            "level_mm": None if c.level_mm is None else round(c.level_mm, 4),
            "degree": c.curve.degree,
            "periodic": c.curve.periodic,
            "control_points": np.round(scanner.control_points, 6).tolist(),
            "knots": np.round(scanner.knots, 12).tolist(),
            "tolerance_mm": c.tolerance_mm,
            "max_deviation_mm": round(c.max_deviation_mm, 5),
            "rms_deviation_mm": round(c.rms_deviation_mm, 5),
            "within_tolerance": c.within_tolerance,
            "exceeds_tolerance_by_mm": round(max(0.0, c.max_deviation_mm - c.tolerance_mm), 5),
            "repairs": list(c.repairs),
        })
    return {
        "coordinates": "input (scanner) coordinates, mm",
        "regions": contours.summary(),
        "shaft_loft_error_p99_mm": round(contours.shaft_fit_error_mm, 4),
        "notes": list(contours.notes),
        "curves": curves,
    }


@exporter("curves", "json")
def curves_json(contours: ContourSet, out_dir: Path) -> Path:
    return write_json(contours_dict(contours), out_dir / "curves.json")


@exporter("tspline", "json")
def tspline_json(model: TSplineModel, out_dir: Path) -> Path:
    """tspline.json: the tube and the caps as T-splines (T-mesh, knot intervals, control points)."""
    doc = {
        "format": "bonecad.tspline_model",
        "version": 1,
        "units": "mm",
        "coordinates": "input (scanner) coordinates",
        "tube": to_dict(to_scanner(model.tspline, model.frame)),
        "caps": {c.end: to_dict(to_scanner(c.tspline, model.frame)) for c in model.caps},
        "summary": {key: value for key, value in model.summary().items() if key != "timings_s"},
    }
    return write_json(doc, out_dir / "tspline.json", indent=None)


@dataclass(frozen=True)
class PatchDocument:
    """``bonecad patch``'s result: the footprint (bone coordinates), the frame's axes (3, 3) and origin (3,)
    that map it to scanner coordinates, its deviation from the mesh, and the plate blank OpenCascade made
    of it."""

    footprint: Footprint
    axes: np.ndarray
    origin: np.ndarray
    mesh_deviation: dict
    plate_blank: dict

    @property
    def surface(self) -> BSplineSurface:
        """The patch in scanner coordinates (an affine map of the poles: exact), its normal S_u x S_v
        out of the bone (v reversed where the frame is mirrored, a left tibia's)."""
        scanner = self.footprint.surface.transformed(self.axes, self.origin)
        return scanner.reversed_v() if np.linalg.det(self.axes) < 0 else scanner


@exporter("patch", "json")
def patch_json(doc: PatchDocument, out_dir: Path) -> Path:
    """patch.json: the region, its parameters and spans, the surface (scanner mm), its deviations, the plate."""
    surface = doc.surface
    data = {
        "format": "bonecad.patch",
        "version": 1,
        "units": "mm",
        "coordinates": "input (scanner) coordinates",
        **doc.footprint.summary(),
        "deviation_from_mesh": doc.mesh_deviation,
        "plate_blank": doc.plate_blank,
        "surface": {"degree": [surface.degree_u, surface.degree_v], "knots_u": surface.knots_u.tolist(),
                    "knots_v": surface.knots_v.tolist(), "poles": np.round(surface.poles, 9).tolist()},
    }
    return write_json(data, out_dir / "patch.json")
