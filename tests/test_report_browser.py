"""report.html in headless Chromium (Debian's ``chromium``, which scripts/setup.sh installs): a real
tibia's report and the phantom's load without console errors, show the verdicts, and their 3-D views
draw the models."""
from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import TIBIA_DIR
from tests.test_analysis_report import parse_cells

CHROMIUM = shutil.which("chromium")
TIBIA = TIBIA_DIR / "LHDL_CT_tibia_no_fib_r.stl"
#: software WebGL (SwiftShader): CI machines have no GPU
FLAGS = ["--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--enable-logging=stderr", "--v=0"]
#: the 3-D view's canvas (bonecad.export.viewer): its CSS size in pixels and its border's grey
CANVAS_PX, BORDER_RGB = (1200, 700), 153

pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="Chromium is absent (scripts/setup.sh installs "
                                                          "Debian's chromium package)")


@pytest.fixture(scope="module", params=["real tibia", "phantom"])
def report_html(request, tmp_path_factory) -> Path:
    """report.html of LHDL's CT tibia (through the command line) or of the phantom tibia (the demo's bone)."""
    out = tmp_path_factory.mktemp("browser") / "run"
    if request.param == "real tibia":
        from bonecad.run.cli import main

        if not TIBIA.is_file():
            pytest.skip(f"{TIBIA} is absent")
        assert main(["reconstruct", str(TIBIA), "--out", str(out), "-q"]) == 0
    else:
        from bonecad.run.pipeline import reconstruct_bone
        from bonecad.settings import Settings

        reconstruct_bone(request.getfixturevalue("phantom"), out, Settings.load())
    return out / "report.html"


def chromium(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([CHROMIUM, *FLAGS, *args], capture_output=True, text=True, timeout=120)


def test_report_loads_without_console_errors_and_shows_the_verdicts(report_html):
    """The page's scripts log nothing (an uncaught error or a WebGL failure would); the summary's verdict
    badges are in the rendered DOM; the page's load and first 3-D frame take under 3 s; under 15 MB."""
    run = chromium("--dump-dom", report_html.as_uri())
    console = [line for line in run.stderr.splitlines() if ":CONSOLE" in line]
    assert not console, console[:5]
    page = parse_cells(run.stdout)
    assert set(page.verdicts) == {"nurbs", "tspline"}
    assert set(page.verdicts.values()) <= {"met", "not met", "stopped at the data's noise"}
    canvas = re.search(r"<canvas id=\"view-canvas\"[^>]*>", run.stdout)
    assert canvas and 'data-drawn="yes"' in canvas.group(0)
    drawn_ms = int(re.search(r'data-drawn-ms="(\d+)"', canvas.group(0)).group(1))
    assert drawn_ms < 3000
    assert report_html.stat().st_size < 15e6


def test_the_3d_view_draws_the_models(report_html, tmp_path):
    """A screenshot of the whole page: inside the 3-D view's border, the models cover part of the canvas."""
    from PIL import Image

    shot = tmp_path / "report.png"
    run = chromium(f"--screenshot={shot}", "--window-size=1400,2600", report_html.as_uri())
    assert shot.is_file(), run.stderr[-2000:]
    rgb = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    border = np.abs(rgb - BORDER_RGB).max(axis=2) <= 2
    rows = np.flatnonzero(border.sum(axis=1) >= CANVAS_PX[0] - 4)
    pairs = [(a, b) for a in rows for b in rows if abs(b - a - CANVAS_PX[1]) <= 2]
    assert pairs, "the 3-D view's canvas (its border) is not in the screenshot"
    top, bottom = pairs[0]
    cols = np.flatnonzero(border[top + 5:bottom - 5].all(axis=0))
    inside = rgb[top + 2:bottom - 1, cols[0] + 2:cols[-1] - 1]
    drawn = inside.min(axis=2) < 235  # not the white background
    assert 0.03 < drawn.mean() < 0.6
    # coloured by deviation: both reds (mesh outside) and blues (inside) show
    red = (inside[..., 0] - inside[..., 2] > 40).mean()
    blue = (inside[..., 2] - inside[..., 0] > 40).mean()
    assert red > 1e-3 and blue > 1e-3
