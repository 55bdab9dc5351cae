"""A failure in any background job of ``reconstruct`` ends the run at once, while its siblings are still
busy: the job's own error, no output folder, no staging folder, no child left.

Each case makes one background job fail and the work running beside it (in this
process) take 60 s; the run must end within seconds all the same. The jobs are
forked, so they inherit the patched functions.
"""
from __future__ import annotations

import multiprocessing
import time

import pytest

from bonecad.errors import FitError
from bonecad.run import pipeline
from bonecad.run.executor import Fork
from bonecad.settings import Settings

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not Fork.available(), reason="fork is not available on this platform")]

BUSY_S = 60.0
#: from the failure to the end of the run, children stopped and staging removed (s)
ENDS_WITHIN_S = 5.0


def _fails(*args, **kwargs):
    raise FitError(f"injected failure at {time.time():.3f}")


def _busy(*args, **kwargs):
    time.sleep(BUSY_S)
    raise AssertionError("the run went on while a background job had failed")


# (what fails in a background job, what keeps this process busy meanwhile)
CASES = {
    "frame": {"bone_frame": _fails},  # beside the imports of OpenCascade and matplotlib
    "contour curves": {"contour_curves": _fails},  # the same job, after the frame
    "mesh noise": {"mesh_noise": _fails, "curve_files_and_nurbs": _busy},
    "curve files and NURBS": {"curve_files_and_nurbs": _fails, "build_tspline_model": _busy},
    "zebra and continuity": {"zebra_and_continuity": _fails, "model_deviation": _busy},
    "colour map": {"render.deviation_map_png": _fails, "render.zebra_png": _busy},  # the zebra: in a child
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_failing_job_ends_the_run_at_once(case, phantom, tmp_path, monkeypatch):
    import bonecad.render.figures as figures
    import bonecad.tspline_model.model as tspline_model

    for name, replacement in CASES[case].items():
        if name.startswith("render."):
            monkeypatch.setattr(figures, name.split(".", 1)[1], replacement)
        elif name == "build_tspline_model":
            monkeypatch.setattr(tspline_model, name, replacement)
        else:
            monkeypatch.setattr(pipeline, name, replacement)
    out = tmp_path / "out"
    with pytest.raises(FitError, match="injected failure") as info:
        pipeline.reconstruct_bone(phantom, out, Settings.load())
    failed_at = float(str(info.value).rsplit(" ", 1)[1])
    assert time.time() - failed_at < ENDS_WITHIN_S
    assert not out.exists()
    assert not list(tmp_path.glob(".out.staging-*"))
    assert multiprocessing.active_children() == []
