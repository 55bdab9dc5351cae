#!/usr/bin/env bash
# Set up bonecad from nothing on Debian with Python 3.11: system libraries
# (OpenGL/X11 runtime that OpenCascade, VTK and MeshLab link against), FreeCAD
# (the tests open the models in it headless; 0.20.2 on bookworm, ~3 min to
# install measured) and Chromium (tests/test_report_browser.py renders
# report.html headless), then a virtual environment in .venv with bonecad and
# its test tools. Idempotent.
set -euo pipefail
cd "$(dirname "$0")/.."

packages="libgl1 libglx0 libopengl0 libegl1 libglu1-mesa libx11-6 libxrender1 libxext6 libxi6 libsm6 libice6 libfontconfig1 libfreetype6 libgomp1 freecad chromium"
if command -v apt-get >/dev/null 2>&1; then
    missing=""
    for p in $packages; do
        dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"
    done
    if [ -n "$missing" ]; then
        sudo=""
        [ "$(id -u)" -ne 0 ] && sudo="sudo"
        $sudo apt-get update -qq
        DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends $missing
    fi
fi

python=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$python" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e '.[test]'
