"""`bonecad measure`'s file: a tibia's morphometric parameters as JSON or as one CSV row.

JSON: {"input", "side", "frame", "values": {name: value}, "units": {name: unit},
"definitions": {name: definition}} in the order of ``PARAMETERS``. CSV: a header
(input, side, then every parameter name) and one row, so the rows of many
bones stack into one table.
"""
from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path

from bonecad.anatomy.morphometry import PARAMETER_NAMES, PARAMETERS, TibiaMeasurements
from bonecad.errors import InputError
from bonecad.staging import staged_file

#: the file formats of ``bonecad measure --out``, by suffix
SUFFIXES = (".json", ".csv")


@dataclass(frozen=True)
class MeasurementsDocument:
    """One tibia's parameters and the input they were measured on."""

    input_file: str
    measurements: TibiaMeasurements

    def as_dict(self) -> dict:
        """The JSON content; values rounded to 0.001 (mm, degrees)."""
        values = self.measurements.values()
        return {
            "input": self.input_file,
            "side": self.measurements.side,
            "frame": "anatomical: origin plafond centre, x lateral, y anterior, z proximal (a left tibia mirrored)",
            "values": {name: round(values[name], 3) for name in PARAMETER_NAMES},
            "units": {name: unit for name, unit, _ in PARAMETERS},
            "definitions": {name: definition for name, _, definition in PARAMETERS},
        }

    def csv_text(self) -> str:
        """A header and one row."""
        values = self.measurements.values()
        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\n")
        writer.writerow(["input", "side", *PARAMETER_NAMES])
        writer.writerow([self.input_file, self.measurements.side, *(f"{values[n]:.3f}" for n in PARAMETER_NAMES)])
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
