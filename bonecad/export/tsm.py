"""tspline.tsm: the T-spline model as one closed T-spline control cage for Autodesk Fusion
(``TSplineBodies.addByTSMFile``), scanner coordinates in centimetres (``tspline_model.cage``)."""
from __future__ import annotations

from pathlib import Path

from bonecad.export.registry import exporter
from bonecad.splines.tspline import tsm
from bonecad.staging import staged_file
from bonecad.tspline_model.cage import model_cage
from bonecad.tspline_model.model import TSplineModel
from bonecad.tspline_model.template import TemplateShape


@exporter("tspline", "tsm")
def tspline_tsm(model: TSplineModel, out_dir: Path) -> Path:
    return _write_cage(model, out_dir / "tspline.tsm")


@exporter("morph", "tsm")
def morph_tsm(shape: TemplateShape, out_dir: Path) -> Path:
    """morph.tsm: a template shape (``bonecad morph``), bone coordinates in centimetres."""
    return _write_cage(shape, out_dir / "morph.tsm")


def _write_cage(model: TSplineModel | TemplateShape, path: Path) -> Path:
    with staged_file(path) as tmp:
        tsm.write(model_cage(model), tmp)
    return path
