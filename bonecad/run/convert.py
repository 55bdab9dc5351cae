"""``bonecad convert``: a ``.tsm`` T-spline to STEP, like a fitted T-spline (Bezier extraction,
one B-spline face per tensor-product block, sewn into one shell; mm)."""
from __future__ import annotations

from pathlib import Path

from bonecad.splines.tspline import TSpline, read_tspline
from bonecad.staging import staged_output

#: sewing tolerance of the converted faces (mm); neighbours agree to rounding
SEWING_TOLERANCE_MM = 1e-4


def convert_tsm(path: str | Path, out_dir: str | Path) -> tuple[TSpline, Path]:
    """Read ``path`` (InputError, exit 2, when it is malformed or outside bonecad's T-spline rules)
    and write ``out_dir/tspline.step``. Returns (the T-spline, the STEP file)."""
    from bonecad.occ.brep import sew, write_named_step
    from bonecad.occ.tspline import merged_faces

    ts = read_tspline(path)
    faces = [face for face, _ in merged_faces(ts)]
    shell, sewn = (faces[0], faces) if len(faces) == 1 else sew(faces, tolerance_mm=SEWING_TOLERANCE_MM,
                                                                 closed=False)
    with staged_output(out_dir) as stage:
        write_named_step(shell, stage / "tspline.step", "tspline", [("tspline", face) for face in sewn])
    return ts, Path(out_dir) / "tspline.step"
