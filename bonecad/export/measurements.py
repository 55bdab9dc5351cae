"""`bonecad measure`'s file: a tibia's or a femur's morphometric parameters as JSON or as one CSV row.

JSON: {"input", "side", "frame", "values": {name: value}, "units": {name: unit},
"definitions": {name: definition}} in the order of ``PARAMETERS``. CSV: a header
(input, side, then every parameter name) and one row, so the rows of many
bones stack into one table. A value the mesh does not show (a femur's canal on an outer surface) is null
in JSON and empty in CSV.
"""
from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path

from bonecad.anatomy.femur_morphometry import FemurMeasurements
from bonecad.anatomy.morphometry import PARAMETERS, TibiaMeasurements
from bonecad.errors import InputError
from bonecad.staging import staged_file

#: the file formats of ``bonecad measure --out``, by suffix
SUFFIXES = (".json", ".csv")


@dataclass(frozen=True)
class MeasurementsDocument:
    """One bone's parameters and the input they were measured on."""

    input_file: str
    measurements: TibiaMeasurements | FemurMeasurements

    @property
    def parameters(self) -> tuple[tuple[str, str, str], ...]:
        """(name, unit, definition) of the bone's parameters."""
        return getattr(self.measurements, "parameters", PARAMETERS)

    @property
    def bone(self) -> str:
        return getattr(self.measurements, "bone", "tibia")

    def as_dict(self) -> dict:
        """The JSON content; values rounded to 0.001 (mm, degrees)."""
        values = self.measurements.values()
        origin = "knee centre (on the anatomical axis)" if self.bone == "femur" else "plafond centre"
        return {
            "input": self.input_file,
            "bone": self.bone,
            "side": self.measurements.side,
            "frame": f"anatomical: origin {origin}, x lateral, y anterior, z proximal (a left {self.bone} mirrored)",
            "values": {name: None if math.isnan(values[name]) else round(values[name], 3)
                       for name, _, _ in self.parameters},
            "units": {name: unit for name, unit, _ in self.parameters},
            "definitions": {name: definition for name, _, definition in self.parameters},
        }

    def csv_text(self) -> str:
        """A header and one row."""
        values = self.measurements.values()
        names = [name for name, _, _ in self.parameters]
        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\n")
        writer.writerow(["input", "side", *names])
        writer.writerow([self.input_file, self.measurements.side,
                         *("" if math.isnan(values[n]) else f"{values[n]:.3f}" for n in names)])
        return out.getvalue()


def check_measurements_path(path: Path) -> None:
    """InputError unless ``path`` names a JSON or CSV file."""
    if path.suffix.lower() not in SUFFIXES:
        raise InputError(f"unsupported measurements format '{path.suffix}' (use {' or '.join(SUFFIXES)})", path)


def write_measurements(doc: MeasurementsDocument, path: Path) -> Path:
    """Write ``doc`` as JSON or CSV, by the suffix of ``path`` (all or nothing)."""
    check_measurements_path(path)
    text = doc.csv_text() if path.suffix.lower() == ".csv" else json.dumps(doc.as_dict(), indent=1) + "\n"
    with staged_file(path) as tmp:
        tmp.write_text(text)
    return path
