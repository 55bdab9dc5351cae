"""tspline.tsm: the T-spline model as one closed T-spline control cage for Autodesk Fusion
(``TSplineBodies.addByTSMFile``), scanner coordinates in centimetres (``tspline_model.cage``)."""
from __future__ import annotations

from pathlib import Path

from bonecad.export.registry import exporter
from bonecad.splines.tspline import tsm
from bonecad.staging import staged_file
from bonecad.tspline_model.cage import model_cage
from bonecad.tspline_model.model import TSplineModel


@exporter("tspline", "tsm")
def tspline_tsm(model: TSplineModel, out_dir: Path) -> Path:
    path = out_dir / "tspline.tsm"
    with staged_file(path) as tmp:
        tsm.write(model_cage(model), tmp)
    return path
