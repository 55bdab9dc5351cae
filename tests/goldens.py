"""Regression of deviation histograms against stored goldens (JSON under ``data/goldens/``).

A golden is the :meth:`Histogram.to_dict` of a known-good run plus a note. A
check fails when any band's share moves by more than ``tolerance`` (absolute
share of surface, e.g. 0.01 = one percentage point) or the bands differ.

Updating on purpose: set ``BONECAD_UPDATE_GOLDENS=1`` (any value but ''/'0')
and run the tests, e.g. ``BONECAD_UPDATE_GOLDENS=1 pytest tests/test_analysis_report.py``;
every checked golden is rewritten from the current result and the check passes.
Review the diff of ``data/goldens/`` before committing it.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bonecad.errors import InputError
from bonecad.staging import staged_file
from bonecad.analysis.statistics import Histogram

#: environment variable that switches golden checks to update mode
UPDATE_ENV = "BONECAD_UPDATE_GOLDENS"
#: top-level ``data/goldens`` of the repository (not package data)
GOLDEN_DIR = Path(__file__).resolve().parents[1] / "data" / "goldens"


class GoldenMismatch(AssertionError):
    """A histogram moved beyond the tolerance from its golden (message lists the bands)."""


@dataclass(frozen=True)
class GoldenComparison:
    """difference : (B+2,) current - golden share per band; worst : largest |difference|."""

    name: str
    difference: np.ndarray
    worst: float
    tolerance: float
    updated: bool

    @property
    def ok(self) -> bool:
        return self.updated or self.worst <= self.tolerance


def update_requested() -> bool:
    return os.environ.get(UPDATE_ENV, "") not in ("", "0")


def golden_path(name: str, golden_dir: str | Path | None = None) -> Path:
    if not name or any(c in name for c in "/\\") or name.startswith("."):
        raise InputError(f"golden name must be a plain file stem, got {name!r}")
    return Path(golden_dir or GOLDEN_DIR) / f"{name}.json"


def write_golden(hist: Histogram, name: str, *, golden_dir: str | Path | None = None, note: str = "") -> Path:
    path = golden_path(name, golden_dir)
    payload = {"name": name, "note": note, "histogram": hist.to_dict()}
    with staged_file(path) as tmp:
        tmp.write_text(json.dumps(payload, indent=1) + "\n")
    return path


def read_golden(name: str, *, golden_dir: str | Path | None = None) -> Histogram:
    path = golden_path(name, golden_dir)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(
            f"no golden '{name}' (expected {path}); create it with {UPDATE_ENV}=1", path
        ) from None
    return Histogram.from_dict(data["histogram"])


def compare_histogram(
    hist: Histogram,
    name: str,
    *,
    tolerance: float = 0.01,
    golden_dir: str | Path | None = None,
    update: bool | None = None,
    note: str = "",
) -> GoldenComparison:
    """Compare ``hist`` with golden ``name`` band by band; in update mode rewrite the golden first.

    ``update`` None means: follow the ``BONECAD_UPDATE_GOLDENS`` environment variable.
    """
    if update is None:
        update = update_requested()
    if update:
        write_golden(hist, name, golden_dir=golden_dir, note=note)
        return GoldenComparison(name, np.zeros_like(hist.shares), 0.0, tolerance, True)
    golden = read_golden(name, golden_dir=golden_dir)
    if golden.edges_mm.shape != hist.edges_mm.shape or not np.allclose(golden.edges_mm, hist.edges_mm):
        raise GoldenMismatch(f"golden '{name}' has other bands than the histogram; update it on purpose")
    diff = hist.shares - golden.shares
    return GoldenComparison(name, diff, float(np.abs(diff).max()), tolerance, False)


def assert_histogram_matches(hist: Histogram, name: str, **kwargs) -> GoldenComparison:
    """:func:`compare_histogram`, raising :class:`GoldenMismatch` naming every band out of tolerance."""
    result = compare_histogram(hist, name, **kwargs)
    if not result.ok:
        labels = hist.labels()
        bad = np.flatnonzero(np.abs(result.difference) > result.tolerance)
        lines = [
            f"  band {labels[i]} mm: {100 * (hist.shares[i] - result.difference[i]):.2f} % -> "
            f"{100 * hist.shares[i]:.2f} %"
            for i in bad
        ]
        raise GoldenMismatch(
            f"deviation histogram '{name}' moved by up to {100 * result.worst:.2f} percentage points "
            f"(tolerance {100 * result.tolerance:.2f}):\n" + "\n".join(lines)
            + f"\nIf the change is intended: {UPDATE_ENV}=1 pytest ..."
        )
    return result


def assert_fairness_matches(figures: dict[str, float], name: str, *, rel_tolerance: float = 0.05,
                            golden_dir: str | Path | None = None, update: bool | None = None) -> None:
    """The fairness figures (name -> 1/mm^2: overall and per region, ``analysis.fairness``) against golden
    ``name`` (JSON ``{"fairness": {...}}``), each within ``rel_tolerance`` of its golden value; in update
    mode (``BONECAD_UPDATE_GOLDENS``) the golden is rewritten first."""
    path = golden_path(name, golden_dir)
    if update_requested() if update is None else update:
        with staged_file(path) as tmp:
            tmp.write_text(json.dumps({"name": name, "units": "1/mm^2", "fairness": figures}, indent=1) + "\n")
        return
    try:
        golden = json.loads(path.read_text())["fairness"]
    except FileNotFoundError:
        raise InputError(f"no golden '{name}' (expected {path}); create it with {UPDATE_ENV}=1", path) from None
    if set(golden) != set(figures):
        raise GoldenMismatch(f"fairness golden '{name}' has other entries ({sorted(golden)}) than {sorted(figures)}")
    bad = [f"  {k}: {golden[k]:.6g} -> {v:.6g} /mm^2" for k, v in figures.items()
           if abs(v - golden[k]) > rel_tolerance * abs(golden[k])]
    if bad:
        raise GoldenMismatch(f"fairness '{name}' moved by more than {100 * rel_tolerance:.0f} %:\n" + "\n".join(bad)
                             + f"\nIf the change is intended: {UPDATE_ENV}=1 pytest ...")
