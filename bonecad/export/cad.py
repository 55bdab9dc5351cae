"""STEP and IGES exporters: the models (one named solid, faces by region) and the contour curves
with the frame's reference entities (named curves, points, lines, planes), in scanner mm."""
from __future__ import annotations

from pathlib import Path

from bonecad.contours.curves import ContourSet
from bonecad.export.registry import exporter
from bonecad.export.documents import FrameDocument, PatchDocument
from bonecad.nurbs_model.model import NurbsModel
from bonecad.occ import brep
from bonecad.occ.curves import to_edge
from bonecad.occ.exchange import frame_entities, write_iges, write_step
from bonecad.occ.surfaces import make_face
from bonecad.tspline_model.model import TSplineModel
from bonecad.tspline_model.template import TemplateShape


def _curve_tree(contours: ContourSet):
    """(name, [groups]): every contour curve (mapped back to scanner coordinates, exact: an affine map
    of the poles) and the reference entities."""
    frame = contours.frame
    curves = [(c.name, to_edge(c.curve.transformed(frame.axes, frame.origin), c.name)) for c in contours.all_curves()]
    return ("bonecad_curves", [("contour_curves", curves), ("reference_entities", frame_entities(frame))])


@exporter("curves", "step")
def curves_step(contours: ContourSet, out_dir: Path) -> Path:
    return write_step(_curve_tree(contours), out_dir / "curves.step")


@exporter("curves", "iges")
def curves_iges(contours: ContourSet, out_dir: Path) -> Path:
    return write_iges(_curve_tree(contours), out_dir / "curves.iges")


@exporter("frame", "step")
def frame_step(doc: FrameDocument, out_dir: Path) -> Path:
    """The reference entities alone, as curves.step (``bonecad frame``)."""
    return write_step(("reference_entities", frame_entities(doc.frame)), out_dir / "curves.step")


def _register_model_exporter(kind: str, fmt: str) -> None:
    """``{kind}.{fmt}``: the model's solid named ``kind``, every face named by its region (scanner mm)."""
    write = brep.write_named_step if fmt == "step" else brep.write_named_iges

    @exporter(kind, fmt)
    def model_file(model: NurbsModel | TSplineModel | TemplateShape, out_dir: Path) -> Path:
        return write(model.shape, out_dir / f"{kind}.{fmt}", kind, list(model.face_names))


for _kind in ("nurbs", "tspline", "morph"):
    for _fmt in ("step", "iges"):
        _register_model_exporter(_kind, _fmt)


def _register_patch_exporter(fmt: str) -> None:
    """``patch.{fmt}``: the footprint as one untrimmed B-spline face named by its region (scanner mm)."""
    write = brep.write_named_step if fmt == "step" else brep.write_named_iges

    @exporter("patch", fmt)
    def patch_file(doc: PatchDocument, out_dir: Path) -> Path:
        face = make_face(doc.surface)
        name = doc.footprint.region.name
        # the face is the whole shape: STEP names its ADVANCED_FACE, IGES the shape's label
        return write(face, out_dir / f"patch.{fmt}", name, [(name, face)] if fmt == "step" else [])


for _fmt in ("step", "iges"):
    _register_patch_exporter(_fmt)
