"""A rough segmentation (tests/rough.py: TLEM2's tibia with smooth random bumps up to 1 mm, decimated to
1.8 mm edges with slivers up to 13 mm): the T-spline is a valid closed solid, its fit stops at the mesh's
noise and says so, and it is at least as close to the clean tibia underneath as the rough mesh itself."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from tests.conftest import REAL_MESHES
from tests.defaults import BANDS_MM, SETTINGS, TESSELLATION

pytestmark = pytest.mark.skipif(not REAL_MESHES, reason="the real meshes folder ../shared/data/tibia is absent")


@pytest.fixture(scope="module")
def rough_run(tmp_path_factory):
    from bonecad.run.pipeline import reconstruct
    from tests.rough import SOURCE, build_rough

    if not SOURCE.is_file():
        pytest.skip(f"{SOURCE} is absent (the rough mesh is made from it)")
    rough = build_rough()
    folder = tmp_path_factory.mktemp("rough")
    mesh = folder / "rough.stl"
    trimesh.Trimesh(rough.vertices, rough.faces, process=False).export(mesh)
    settings = SETTINGS.replace("pipeline", models=("tspline",))
    return rough, reconstruct(mesh, folder / "out", settings)


def test_rough_mesh_is_rough(rough_run):
    rough, _ = rough_run
    assert 1.5 <= rough.median_edge_mm <= 2.5 and rough.max_edge_mm >= 10.0


def test_rough_mesh_gives_a_valid_closed_tspline_no_farther_from_the_clean_tibia(rough_run):
    from bonecad.analysis.deviation import shape_deviation
    from bonecad.mesh.closest import TriangleLocator
    from bonecad.occ.brep import is_valid
    from bonecad.occ.exchange import read_step
    from bonecad.occ.tessellate import tessellate

    rough, result = rough_run
    solids = read_step(result.out_dir / "tspline.step").solids()
    assert len(solids) == 1 and is_valid(solids[0].wrapped)
    clean = trimesh.Trimesh(rough.clean_vertices, rough.clean_faces, process=False)
    samples, _ = trimesh.sample.sample_surface(clean, 100_000, seed=3)
    rough_share = float(np.mean(TriangleLocator(rough.vertices, rough.faces).query(samples).distance <= 0.25))
    deviation = shape_deviation(rough.clean_vertices, rough.clean_faces, tessellate(solids[0].wrapped, TESSELLATION),
                                sample_points=100_000, edges_mm=BANDS_MM)
    # measured: rough mesh 0.781, T-spline 0.785 when the stop waited for the share (2387 control points);
    # stopped at the first round at the noise level with rough_mark_factor's small rounds, 1544 control points,
    # about 0.787 (0.780 at 1929 with rounds marking 60 % of the residual above the noise: a round past the
    # bone's scale follows the bumps). The bumps are smooth at the fit's scale (benchmarks/bench_noise.py)
    assert deviation.mesh_to_cad.share_within(0.25) >= rough_share


def test_rough_mesh_fit_stops_at_the_noise_and_says_so(rough_run):
    import json

    _, result = rough_run
    report = json.loads((result.out_dir / "report.json").read_text())
    info = report["models"]["tspline"]["info"]
    assert info["noise_level_mm"] >= SETTINGS.tspline.rough_noise_level_mm  # measured 0.149 mm
    assert info["fit_stopped"].startswith("stopped at the data's noise"), info["fit_stopped"]
    # chasing the bumps' peaks below 1 mm took 2418 control points; stopped at the share and the noise, 2387;
    # at the first round at the noise level (issue 48), 1544: under the clean TLEM2 tibia's 2013
    assert info["fit"]["control_points"] < 2013


def test_contour_curves_of_a_coarse_rough_mesh_stay_on_their_sections(tmp_path):
    """At 2.5 mm edges a curve with 70 control points has sections with points 4 mm apart round sharp folds:
    the first fit overshot by 56 mm there; the stiffer refit keeps every curve on its section."""
    import bonecad
    from bonecad.contours.curves import contour_curves
    from tests.rough import SOURCE, build_rough

    if not SOURCE.is_file():
        pytest.skip(f"{SOURCE} is absent (the rough mesh is made from it)")
    rough = build_rough(faces=12000, bumps=400, bump_radius_mm=(3.0, 6.0))  # 2.5 mm edges
    mesh = tmp_path / "rough.stl"  # read as a user's file is (STL: float32 vertices, one triple per face)
    trimesh.Trimesh(rough.vertices, rough.faces, process=False).export(mesh)
    bone = bonecad.load_bone(mesh, settings=SETTINGS)
    frame = bonecad.anatomical_frame(bone, SETTINGS)
    curves = contour_curves(bone, frame, settings=SETTINGS.curves).all_curves()
    assert max(c.max_deviation_mm for c in curves) < 0.25  # measured 0.127 mm
    assert any(any("refitted stiffer" in r for r in c.repairs) for c in curves)
