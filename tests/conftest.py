"""Shared fixtures: the phantom tibia, the real meshes in ../shared/data, a seeded RNG."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("BONECAD_DATA", ROOT.parent / "shared" / "data"))
TIBIA_DIR = DATA / "tibia"
REAL_MESHES = sorted(TIBIA_DIR.glob("*.stl")) if TIBIA_DIR.is_dir() else []
# Sides as the data README states them (file names are never used by bonecad itself).
README_SIDES = {"JIA_MRI_tibia_l.stl": "left"}


def real_mesh_params():
    """pytest params over the real meshes, or one skipped param saying why."""
    if not REAL_MESHES:
        return [pytest.param(None, marks=pytest.mark.skip(reason=f"real meshes folder {TIBIA_DIR} is absent"))]
    return [pytest.param(p, id=p.stem) for p in REAL_MESHES]


@pytest.fixture(scope="session")
def phantom():
    import bonecad

    return bonecad.phantom_tibia()


@pytest.fixture(scope="session")
def phantom_frame(phantom):
    import bonecad

    return bonecad.anatomical_frame(phantom)


@pytest.fixture
def rng():
    return np.random.default_rng(0)
