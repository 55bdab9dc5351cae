"""Shared fixtures: the phantom tibia, the real meshes in ../shared/data, a seeded RNG, and the CLI runs
several test modules read (run once per session: each takes tens of seconds)."""
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


@pytest.fixture(scope="session")
def phantom_contours(phantom, phantom_frame):
    """The phantom's contour curves (shipped settings)."""
    from bonecad.contours.curves import contour_curves

    from .defaults import SETTINGS

    return contour_curves(phantom, phantom_frame, settings=SETTINGS.curves)


@pytest.fixture(scope="session")
def phantom_tspline_model(phantom, phantom_frame, phantom_contours):
    """The phantom's T-spline model (shipped settings): fitted tube, apex caps, sewn solid."""
    from bonecad.tspline_model import build_tspline_model

    from .defaults import SETTINGS

    return build_tspline_model(phantom, phantom_frame, phantom_contours, settings=SETTINGS.tspline,
                               apex_hole_radius_mm=SETTINGS.curves.apex_hole_radius_mm)


@pytest.fixture(scope="session")
def varied_phantoms():
    """The 20 varied phantoms (``cohorts.varied_parameters``) meshed once for the session (shipped settings): the
    measure's tests use them. [(TibiaParameters, BoneMesh)]"""
    from .cohorts import varied_parameters

    params = varied_parameters()
    return list(zip(params, phantoms_on_both_cores(params)))


def phantoms_on_both_cores(params: list) -> list:
    """The phantom of each of ``params`` (shipped settings), made two at a time in forked children: 1.5-2 s
    each at 1 mm, and the fixtures need 34 of them."""
    from bonecad.imaging.phantom_tibia import phantom_tibia
    from bonecad.run.executor import executor_for

    from .defaults import SETTINGS

    bones = []
    with executor_for(True) as ex:
        for start in range(0, len(params), 2):
            jobs = [ex.submit(phantom_tibia, p, settings=SETTINGS.mesh, plausible=SETTINGS.units)
                    for p in params[start : start + 2]]
            bones += [job.result() for job in jobs]
    return bones


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.fixture(scope="session")
def fused_tibia_fibula(tmp_path_factory):
    """TLEM2's tibia and fibula voxelised at 1 mm into one body (tests/fused.py): (STL path, FusedMesh)."""
    from .fused import SOURCE, build_fused, write_fused

    if not SOURCE.is_file():
        pytest.skip(f"{SOURCE} is absent (the fused tibia-fibula mesh is built from it)")
    fused = build_fused(SOURCE)
    return write_fused(tmp_path_factory.mktemp("fused") / "TLEM2_fused_1mm.stl", fused), fused


#: the smallest real tibia (MRI, right side): the real input the CLI-level tests reconstruct
SMALL_REAL_TIBIA = TIBIA_DIR / "ICL_MRI_tibia_r.stl"


def _cli(args: list[str]) -> None:
    from bonecad.run.cli import main

    assert main([*args, "-q"]) == 0, f"bonecad {' '.join(args)} failed"


@pytest.fixture(scope="session")
def phantom_run(tmp_path_factory, phantom) -> Path:
    """``bonecad reconstruct`` of the phantom mesh (both models, shipped settings): its output folder."""
    folder = tmp_path_factory.mktemp("phantom_run")
    mesh = folder / "phantom.stl"
    phantom.to_trimesh().export(mesh)
    _cli(["reconstruct", str(mesh), "--out", str(folder / "out")])
    return folder / "out"


@pytest.fixture(scope="session")
def real_tibia_run(tmp_path_factory) -> Path:
    """``bonecad reconstruct`` of ICL's MRI tibia (both models, shipped settings): its output folder."""
    if not SMALL_REAL_TIBIA.is_file():
        pytest.skip(f"the real tibia {SMALL_REAL_TIBIA} is absent (the shared data folder is not mounted)")
    out = tmp_path_factory.mktemp("real_tibia_run") / "out"
    _cli(["reconstruct", str(SMALL_REAL_TIBIA), "--out", str(out)])
    return out


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory) -> Path:
    """``bonecad demo``: the phantom imaged as a CT and reconstructed; its output folder."""
    out = tmp_path_factory.mktemp("demo_run") / "out"
    _cli(["demo", "--out", str(out)])
    return out
