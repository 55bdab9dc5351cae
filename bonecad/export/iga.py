"""tspline.iga: the T-spline model in the Rhino T-Splines ``.iga`` format, scanner coordinates (mm), for
isogeometric analysis (``splines.tspline.iga``).

The file holds the tube's own T-spline basis (C2) and the two apex caps: each cap's pole row as one
function (its collapsed row's functions, one by one, are not in H^1 at the pole: summed they are), its ring
row written in the tube's end-row functions (C0 across the ring, watertight), its two inner rows as
functions of their own. Sets: side sets ``distal_ring`` / ``proximal_ring`` (the tube's end edges, BOTTOM
/ TOP), element sets ``tube``, ``distal_cap``, ``proximal_cap``, node sets ``distal_pole``,
``proximal_pole``.
"""
from __future__ import annotations

import json
from pathlib import Path

from bonecad.export.registry import exporter
from bonecad.splines.tspline import TSpline, from_dict
from bonecad.splines.tspline.iga import closed_surface, iga_text
from bonecad.staging import staged_file
from bonecad.tspline_model.model import TSplineModel, to_scanner

COMMENT = """bonecad tspline.iga: a T-spline bone surface (tube and two apex caps), scanner coordinates, mm.
Elements: the tube's Bezier elements, then the distal cap's, then the proximal cap's.
Each cap's collapsed pole row is one basis function (node set <end>_pole); its ring row is written in
the tube's end functions (C0 across the ring); the tube's functions are its T-spline basis (C2)."""


def write_iga(tube: TSpline, caps: dict[str, TSpline], path: Path) -> Path:
    """Write the tube and its caps (scanner mm) to ``path``."""
    surface = closed_surface(tube, [(end, caps[end]) for end in ("distal", "proximal")])
    with staged_file(path) as tmp:
        tmp.write_text(iga_text(surface, COMMENT))
    return path


@exporter("tspline", "iga")
def tspline_iga(model: TSplineModel, out_dir: Path) -> Path:
    return write_iga(to_scanner(model.tspline, model.frame),
                     {c.end: to_scanner(c.tspline, model.frame) for c in model.caps}, out_dir / "tspline.iga")


def iga_from_json(tspline_json: Path, out_dir: Path) -> Path:
    """tspline.iga from a reconstruction's tspline.json (tube and caps, scanner coordinates)."""
    doc = json.loads(Path(tspline_json).read_text())
    return write_iga(from_dict(doc["tube"]), {end: from_dict(d) for end, d in doc["caps"].items()},
                     out_dir / "tspline.iga")
