"""Save and load T-splines as JSON; floats are written by ``repr`` so a load
gives back bit-identical arrays.

Layout (version 1)::

    {"format": "bonecad.tspline", "version": 1,
     "s_lines": [...], "t_lines": [...], "s_period": float | null,
     "s_edges": [[t_line, first_segment, end_segment], ...],   # runs, end exclusive
     "t_edges": [[s_line, first_segment, end_segment], ...],
     "control_points": [[x, y, z], ...],  # mm, in anchor order (t-line, then s-line)
     "weights": [...]}

Knot intervals are the differences of consecutive line values; the topology
(which unit edges exist) is the run-length-coded edge arrays.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bonecad.errors import InputError
from bonecad.splines.tspline.tmesh import TMesh
from bonecad.splines.tspline.tspline import TSpline

FORMAT = "bonecad.tspline"
VERSION = 1


def _runs(edges: np.ndarray) -> list[list[int]]:
    """(rows, segments) bool -> [[row, start, end), ...] runs of True."""
    pad = np.zeros((edges.shape[0], 1), dtype=np.int8)
    d = np.diff(np.hstack([pad, edges.astype(np.int8), pad]), axis=1)
    r0, c0 = np.nonzero(d == 1)
    _, c1 = np.nonzero(d == -1)
    return np.stack([r0, c0, c1], axis=1).tolist()


def _unruns(runs, shape: tuple[int, int], name: str) -> np.ndarray:
    out = np.zeros(shape, dtype=bool)
    for run in runs:
        if len(run) != 3:
            raise InputError(f"{name}: expected [row, start, end] runs, got {run!r}")
        r, a, b = (int(x) for x in run)
        if not (0 <= r < shape[0] and 0 <= a < b <= shape[1]):
            raise InputError(f"{name}: run {run!r} outside the grid {shape}")
        out[r, a:b] = True
    return out


def to_dict(ts: TSpline) -> dict:
    """The T-spline as a JSON-ready dict."""
    m = ts.mesh
    return {
        "format": FORMAT,
        "version": VERSION,
        "s_lines": m.s_lines.tolist(),
        "t_lines": m.t_lines.tolist(),
        "s_period": m.s_period,
        "s_edges": _runs(m.s_edges),
        "t_edges": _runs(m.t_edges),
        "control_points": ts.control_points.tolist(),
        "weights": ts.weights.tolist(),
    }


def from_dict(data: dict) -> TSpline:
    """Rebuild a T-spline from ``to_dict`` output; InputError on anything malformed."""
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InputError(f"not a {FORMAT} document")
    if data.get("version") != VERSION:
        raise InputError(f"unsupported {FORMAT} version {data.get('version')!r} (expected {VERSION})")
    try:
        s_lines = np.asarray(data["s_lines"], dtype=np.float64)
        t_lines = np.asarray(data["t_lines"], dtype=np.float64)
        period = data["s_period"]
        period = None if period is None else float(period)
        s_n, t_n = len(s_lines), len(t_lines)
        s_seg = s_n if period is not None else s_n - 1
        s_edges = _unruns(data["s_edges"], (t_n, s_seg), "s_edges")
        t_edges = _unruns(data["t_edges"], (s_n, t_n - 1), "t_edges")
        cp, w = data["control_points"], data["weights"]
        mesh = TMesh(s_lines, t_lines, s_edges, t_edges, period)
        mesh.validate()
        return TSpline(mesh, np.asarray(cp, dtype=np.float64).reshape(-1, 3), np.asarray(w, dtype=np.float64))
    except (KeyError, TypeError, ValueError) as exc:  # the kernel's ValueError: the document is at fault
        raise InputError(f"malformed {FORMAT} document: {exc}") from exc


def save(ts: TSpline, path: str | Path) -> Path:
    """Write the T-spline as JSON to ``path``."""
    path = Path(path)
    path.write_text(json.dumps(to_dict(ts)))
    return path


def load(path: str | Path) -> TSpline:
    """Read a T-spline written by ``save``."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"cannot read T-spline JSON: {exc}", path) from exc
    return from_dict(data)
