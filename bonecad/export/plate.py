"""Plate exporters: plate.step/.iges/.stl (the solid), plate_curves.step (centre line and screw axes),
screws.csv and plate.json (the fit report), all in scanner coordinates, mm."""
from __future__ import annotations

import csv
import dataclasses
import io
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bonecad.export.documents import write_json
from bonecad.export.registry import exporter
from bonecad.staging import staged_file
from bonecad.tspline_model.patch import PatchRegion
from bonecad.tspline_model.plate import Fixation, PlatePlan, Screw


@dataclass(frozen=True)
class PlateDocument:
    """``bonecad plate``'s result: the region asked for, the plan (bone coordinates; its footprint is the face
    about the region's middle angle), the frame's axes (3, 3) and origin (3,) that map it to scanner
    coordinates, the OpenCascade solid and its check (solids, valid, volume_mm3), the stage times (s), and on a
    fracture the fixation (its screws are the plan's)."""

    region: PatchRegion
    plan: PlatePlan
    axes: np.ndarray
    origin: np.ndarray
    solid: Any
    check: dict
    seconds: dict
    fixation: Fixation | None = None

    def point(self, p: np.ndarray) -> np.ndarray:
        return np.asarray(p) @ self.axes + self.origin

    def vector(self, d: np.ndarray) -> np.ndarray:
        return np.asarray(d) @ self.axes

    @property
    def mass_g(self) -> float:
        return self.check["volume_mm3"] / 1000.0 * self.plan.settings.density_g_cm3

    @property
    def failing(self) -> list[dict]:
        return [{"hole": s.hole, "why": list(s.warnings)} for s in self.plan.screws if s.warnings]


def _round(values: np.ndarray, digits: int = 4) -> list[float]:
    return [round(float(v), digits) for v in values]


def _screw_row(doc: PlateDocument, screw: Screw) -> dict:
    return {
        "hole": screw.hole,
        "head": _round(doc.point(screw.head)), "entry": _round(doc.point(screw.entry)),
        "direction": _round(doc.vector(screw.direction), 6),
        "length_mm": round(screw.length_mm, 3), "stock_mm": screw.stock_mm,
        "exit": _round(doc.point(screw.exit)),
        "bone_path_mm": round(float(np.linalg.norm(screw.exit - screw.entry)), 3),
        "outside_bone_mm": round(screw.outside_mm, 3),
        "clearance_mm": round(screw.clearance_mm, 3) if np.isfinite(screw.clearance_mm) else None,
        "exit_height_mm": round(float(screw.exit[2]), 3),
        "warnings": list(screw.warnings),
    }


@exporter("plate", "json")
def plate_json(doc: PlateDocument, out_dir: Path) -> Path:
    """plate.json: the region, the design, the solid's check, volume and mass, the fit and the screws."""
    plan = doc.plan
    data = {
        "format": "bonecad.plate",
        "version": 1,
        "units": "mm",
        "coordinates": "input (scanner) coordinates",
        "region": {"name": doc.region.name, "height_mm": list(doc.region.height_mm),
                   "angle_deg": list(doc.region.angle_deg)},
        "face": plan.footprint.summary()["spans"],
        "design": dataclasses.asdict(plan.settings),
        "plate": {**doc.check, "mass_g": round(doc.mass_g, 3), "length_mm": round(plan.length_mm, 3),
                  "underside_offset_mm": round(plan.offset_mm, 4), "underside_smoothing_mm": plan.smoothing_mm,
                  "holes": len(plan.hole_y)},
        "fit": plan.fit_summary(),
        "joints": {"distal_apex_height_mm": round(plan.joint_heights_mm[0], 3),
                   "proximal_apex_height_mm": round(plan.joint_heights_mm[1], 3)},
        "screws": [_screw_row(doc, s) for s in plan.screws],
        "failing_screws": doc.failing,
        "seconds": {k: round(v, 3) for k, v in doc.seconds.items()},
    }
    if doc.fixation is not None:
        data["fracture"] = doc.fixation.summary()
    return write_json(data, out_dir / "plate.json")


@exporter("plate", "csv")
def screws_csv(doc: PlateDocument, out_dir: Path) -> Path:
    """screws.csv: one row per screw (points and direction in scanner mm)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["hole", "head_x", "head_y", "head_z", "entry_x", "entry_y", "entry_z", "dir_x", "dir_y",
                     "dir_z", "length_mm", "stock_mm", "exit_x", "exit_y", "exit_z", "clearance_mm", "warnings"])
    for screw in doc.plan.screws:
        row = _screw_row(doc, screw)
        writer.writerow([row["hole"], *row["head"], *row["entry"], *row["direction"], row["length_mm"],
                         row["stock_mm"], *row["exit"], row["clearance_mm"], "; ".join(row["warnings"])])
    path = out_dir / "screws.csv"
    with staged_file(path) as tmp:
        tmp.write_text(buffer.getvalue())
    return path


def _register_solid_exporters() -> None:
    """plate.step, plate.iges, plate.stl and plate_curves.step."""

    @exporter("plate", "step")
    def plate_step(doc: PlateDocument, out_dir: Path) -> Path:
        from bonecad.occ.brep import write_named_step

        return write_named_step(doc.solid, out_dir / "plate.step", "plate", [])

    @exporter("plate", "iges")
    def plate_iges(doc: PlateDocument, out_dir: Path) -> Path:
        from bonecad.occ.brep import write_named_iges

        return write_named_iges(doc.solid, out_dir / "plate.iges", "plate", [])

    @exporter("plate", "stl")
    def plate_stl(doc: PlateDocument, out_dir: Path) -> Path:
        from bonecad.occ.plate import write_stl

        return write_stl(doc.solid, out_dir / "plate.stl")

    @exporter("plate", "curves")
    def plate_curves(doc: PlateDocument, out_dir: Path) -> Path:
        from bonecad.occ.exchange import write_step
        from bonecad.occ.plate import polyline_curve_edge, segment_edge

        plan = doc.plan
        items = [("centre_line", polyline_curve_edge(doc.point(plan.centre_points(plan.offset_mm))))]
        items += [(f"screw_{s.hole}_axis", segment_edge(doc.point(s.head), doc.point(s.tip))) for s in plan.screws]
        return write_step(("plate_curves", items), out_dir / "plate_curves.step")


_register_solid_exporters()
