"""FreeCAD as a client of bonecad's STEP files: open one headless (``freecadcmd``) and report its solids.

Used by tests/test_cad_operations.py and benchmarks/bench_cad_ops.py. FreeCAD
runs as its own process (its own OpenCascade), so a file passes only if another
CAD program reads it as bonecad meant it: one valid, closed solid.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

#: FreeCAD's command-line interpreters, in the order tried (Debian: freecadcmd).
COMMANDS = ("freecadcmd", "FreeCADCmd", "freecadcmd-python3")
#: The marker before the JSON line the script prints.
MARKER = "BONECAD_FREECAD "
SCRIPT = """
import json, os, Part
shape = Part.read(os.environ["BONECAD_STEP"])
solids = shape.Solids
print(os.environ["BONECAD_MARKER"] + json.dumps({"version": ".".join(App.Version()[:3]), "solids": len(solids),
    "valid": [s.isValid() for s in solids], "closed": [s.isClosed() for s in solids],
    "volumes_mm3": [s.Volume for s in solids], "faces": len(shape.Faces)}))
"""


@dataclass(frozen=True)
class FreecadVerdict:
    """What FreeCAD made of a STEP file: its solids, their validity and closure, volumes (mm^3), faces."""

    version: str
    solids: int
    valid: tuple[bool, ...]
    closed: tuple[bool, ...]
    volumes_mm3: tuple[float, ...]
    faces: int

    @property
    def one_valid_closed_solid(self) -> bool:
        return self.solids == 1 and all(self.valid) and all(self.closed)

    def summary(self) -> str:
        state = "one valid closed solid" if self.one_valid_closed_solid else (
            f"{self.solids} solids, valid {list(self.valid)}, closed {list(self.closed)}")
        return f"FreeCAD {self.version}: {state}, {self.faces} faces"


def freecad_command() -> str | None:
    """The path of FreeCAD's command-line interpreter, or None when FreeCAD is not installed."""
    for name in COMMANDS:
        found = shutil.which(name)
        if found:
            return found
    return None


def freecad_check(step: Path, *, timeout_s: float = 300.0) -> FreecadVerdict:
    """Open ``step`` in headless FreeCAD and report its solids (RuntimeError when FreeCAD fails)."""
    command = freecad_command()
    if command is None:
        raise RuntimeError("FreeCAD is not installed (freecadcmd not on PATH)")
    env = dict(os.environ, BONECAD_STEP=str(step), BONECAD_MARKER=MARKER, QT_QPA_PLATFORM="offscreen")
    done = subprocess.run([command, "-c", SCRIPT], capture_output=True, text=True, env=env, timeout=timeout_s)
    lines = [line for line in done.stdout.splitlines() if line.startswith(MARKER)]
    if done.returncode != 0 or len(lines) != 1:
        raise RuntimeError(f"freecadcmd failed on {step} (exit {done.returncode}): {done.stderr[-2000:]}"
                           f"{done.stdout[-2000:]}")
    data = json.loads(lines[0][len(MARKER):])
    return FreecadVerdict(data["version"], data["solids"], tuple(data["valid"]), tuple(data["closed"]),
                          tuple(data["volumes_mm3"]), data["faces"])
