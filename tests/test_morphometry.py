"""`bonecad measure`: the phantoms' design values recovered, rigid-motion and mirror invariance, the real
tibias in published adult ranges, the command's files and errors."""
from __future__ import annotations

import csv
import json
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import bonecad
from bonecad.anatomy.morphometry import PARAMETER_NAMES, PARAMETERS, measure_tibia
from bonecad.imaging.phantom_tibia import TibiaParameters, design_measurements
from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.run.cli import main

from .cohorts import PHANTOMS, varied_parameters
from .conftest import TIBIA_DIR, real_mesh_params
from .defaults import SETTINGS
from .test_frame import _moved

MORPH = SETTINGS.morphometry
# The names other code builds on (the cohort table, the shape model's regression, `morph`'s flags).
NAMES = ("length_mm", "max_length_mm", "plateau_width_mm", "medial_plateau_depth_mm", "lateral_plateau_depth_mm",
         "medial_posterior_slope_deg", "lateral_posterior_slope_deg", "plafond_width_mm", "plafond_depth_mm",
         "bimalleolar_width_mm", *(f"shaft_{d}_{p}_mm" for d in ("ml", "ap") for p in (20, 35, 50, 65, 80)),
         "torsion_deg")
# Published adult ranges (docs/validation/anatomy-literature.md: mean +- 2 SD, the union over the cited studies)
# of the parameters for which a source was found.
PUBLISHED = {
    "length_mm": (294.6, 425.0),
    "max_length_mm": (312.0, 482.0),
    "plateau_width_mm": (59.7, 95.4),
    "medial_plateau_depth_mm": (37.7, 61.5),
    "lateral_plateau_depth_mm": (33.1, 53.1),
    "medial_posterior_slope_deg": (-0.1, 15.9),
    "lateral_posterior_slope_deg": (-2.3, 14.7),
    "torsion_deg": (17.7, 52.1),
    # Osteometric caliper measures of dry bones, mean +- 2 SD computed from the individual measurements of the
    # Forensic Data Bank and DPAA reference samples shipped with OsteoSort
    # (docs/validation/anatomy-literature.md: files, commits, definitions).
    "plafond_depth_mm": (23.5, 37.2),
    "bimalleolar_width_mm": (41.0, 58.7),
    "shaft_ap_50_mm": (23.4, 35.1),
    "shaft_ap_65_mm": (26.6, 42.4),
    "shaft_ml_65_mm": (18.3, 30.4),
    # The same from the individuals of the Goldman Osteometric Data Set (bioanth's copy; the same page: commit,
    # columns, what its documentation leaves open).
    "shaft_ml_50_mm": (16.8, 26.6),
}
# The parameters left untested, each with its reason (docs/validation/anatomy-literature.md: what was searched).
_NO_SOURCE = "no published adult mean and SD found for this definition"
UNSOURCED = {
    "plafond_width_mm": _NO_SOURCE + " (the tibial plafond width is named in CT studies, without figures)",
    **{f"shaft_{d}_{p}_mm": _NO_SOURCE + " (csg-dataset: its data files are not readable here; its properties "
       "are areas and second moments, the extents would come from its polygons)"
       for d in ("ml", "ap") for p in (20, 35, 80)},
}

#: issue 21: 1 mm for lengths, 1 degree for angles
TOLERANCE = 1.0


def _measure(bone: BoneMesh) -> dict[str, float]:
    frame = bonecad.anatomical_frame(bone)
    return measure_tibia(bone, frame, MORPH).values()


@pytest.fixture(scope="module")
def phantom_errors(varied_phantoms) -> dict[str, np.ndarray]:
    """Measured minus design value of every parameter of the 20 varied phantoms (mm, degrees)."""
    errors: dict[str, list[float]] = {name: [] for name in PARAMETER_NAMES}
    for params, bone in varied_phantoms:
        measured, design = _measure(bone), design_measurements(params, MORPH)
        for name in PARAMETER_NAMES:
            errors[name].append(measured[name] - design[name])
    return {name: np.array(e) for name, e in errors.items()}


def test_parameter_names_are_the_shared_ones():
    assert PARAMETER_NAMES == NAMES
    assert all(unit == ("deg" if name.endswith("_deg") else "mm") for name, unit, _ in PARAMETERS)


def test_design_values_cover_every_parameter():
    assert set(design_measurements(TibiaParameters(), MORPH)) == set(PARAMETER_NAMES)


def test_default_phantom_parameters_leave_the_phantom_as_it_was():
    """The new parameters (slopes, torsion) default to 0; the golden tests check the mesh itself."""
    p = TibiaParameters()
    assert (p.medial_slope_deg, p.lateral_slope_deg, p.torsion_deg) == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("index", [0, 7])
def test_the_phantom_field_in_blocks_gives_the_mesh_of_the_whole_field(index):
    """The phantom's field is evaluated only in the blocks its surface may cross (``_grid_field``): marching
    cubes must give the same mesh as on the field evaluated at every voxel (two varied phantoms at 2 mm, torsion
    and slopes included)."""
    from skimage.measure import marching_cubes

    from bonecad.imaging.phantom_tibia import _field, _grid, _grid_field

    p = replace(varied_parameters()[index], voxel_mm=2.0)
    xs, ys, zs = _grid(p)
    whole = _field(*np.meshgrid(xs, ys, zs, indexing="ij"), p).astype(np.float32)
    blocks = _grid_field(xs, ys, zs, p).astype(np.float32)
    assert np.array_equal(np.sign(whole), np.sign(blocks))
    for a, b in zip(marching_cubes(whole, 0.0)[:2], marching_cubes(blocks, 0.0)[:2]):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("name", NAMES)
def test_measure_recovers_the_design_of_varied_phantoms(phantom_errors, name):
    worst = float(np.abs(phantom_errors[name]).max())
    assert worst <= TOLERANCE, f"{name}: worst error {worst:.3f} over {PHANTOMS} phantoms"


def test_varied_phantoms_span_the_parameters():
    """The cohort is varied: lengths, widths, slopes and torsion spread over most of their ranges."""
    params = varied_parameters()
    assert len(params) == PHANTOMS
    spread = {"length_mm": 40.0, "plateau_width_mm": 8.0, "medial_slope_deg": 7.0, "lateral_slope_deg": 6.0,
              "torsion_deg": 25.0}
    for field, least in spread.items():
        assert np.ptp([getattr(p, field) for p in params]) > least, field


def test_every_varied_phantom_has_a_tuberosity_that_stands_proud():
    """The tuberosity ellipsoid sits as deep below each phantom's own anterior surface as below the default's:
    on the 20 varied phantoms it stands 3.0-7.6 mm proud of the body underneath (7.1-11 mm high), the default's
    5.19 mm as before. Placed by the shaft depth alone it stood 0.4-9.7 mm proud, 0.4 mm on a phantom with a
    deep plateau and a 7.2 mm tuberosity, where no finder could tell it from the crest."""
    from dataclasses import replace

    from bonecad.imaging.phantom_tibia import _first_exit

    def proud_mm(p: TibiaParameters) -> float:
        start = np.array([[0.1 * p.plateau_width_mm, 0.0, 0.89 * p.length_mm]])
        up = np.array([[0.0, 1.0, 0.0]])
        flat = replace(p, tuberosity_height_mm=1e-3)
        return float(_first_exit(p, start, up, 80.0)[0] - _first_exit(flat, start, up, 80.0)[0])

    assert proud_mm(TibiaParameters()) == pytest.approx(5.19, abs=0.01)
    assert min(proud_mm(p) for p in varied_parameters()) > 2.5


def _assert_invariant(bone: BoneMesh, seed: int) -> None:
    rng = np.random.default_rng(seed)
    reference = _measure(bone)
    rotation = Rotation.random(random_state=seed).as_matrix()
    for mirror in (False, True):
        moved = _measure(_moved(bone, rotation, rng.uniform(-500.0, 500.0, 3), mirror))
        for name in PARAMETER_NAMES:  # issue 21: 0.5 mm, 0.5 degree
            assert abs(moved[name] - reference[name]) <= 0.5, (name, mirror, moved[name], reference[name])


def test_measure_is_invariant_under_rigid_motion_and_mirror_phantom(phantom):
    _assert_invariant(phantom, 3)


def test_measure_is_invariant_under_rigid_motion_and_mirror_real():
    path = TIBIA_DIR / "TLEM2_CT_tibia_r.stl"
    if not path.is_file():
        pytest.skip(f"{path} is absent (a real tibia moved and mirrored)")
    _assert_invariant(bonecad.load_bone(path), 5)


def test_every_parameter_has_a_published_range_or_a_reason_why_not():
    assert set(PUBLISHED).isdisjoint(UNSOURCED)
    assert set(PUBLISHED) | set(UNSOURCED) == set(NAMES)


@pytest.mark.parametrize("path", real_mesh_params())
def test_real_tibias_lie_in_published_adult_ranges(path):
    values = _measure(bonecad.load_bone(path))
    outside = {name: round(values[name], 1) for name, (lo, hi) in PUBLISHED.items() if not lo <= values[name] <= hi}
    assert not outside, f"outside the published adult ranges {PUBLISHED}: {outside}"


def test_measure_command_writes_json_and_csv(tmp_path, capsys):
    stl = tmp_path / "phantom.stl"
    bonecad.phantom_tibia().to_trimesh().export(stl)
    assert main(["measure", str(stl), "--out", str(tmp_path / "m.json"), "-q"]) == 0
    printed = capsys.readouterr().out
    assert "right tibia" in printed and "torsion_deg" in printed
    doc = json.loads((tmp_path / "m.json").read_text())
    assert list(doc["values"]) == list(NAMES) and doc["side"] == "right"
    assert main(["measure", str(stl), "--out", str(tmp_path / "m.csv"), "-q"]) == 0
    rows = list(csv.DictReader((tmp_path / "m.csv").open()))
    assert len(rows) == 1 and all(abs(float(rows[0][n]) - doc["values"][n]) < 2e-3 for n in NAMES)


def test_measure_command_bad_input_exits_2(tmp_path, capsys):
    assert main(["measure", str(tmp_path / "missing.stl")]) == 2
    assert "missing.stl" in capsys.readouterr().err
    stl = tmp_path / "phantom.stl"
    stl.write_text("solid nothing\nendsolid nothing\n")
    assert main(["measure", str(stl), "--out", str(tmp_path / "m.txt")]) == 2
    err = capsys.readouterr().err
    assert "m.txt" in err and ".json or .csv" in err and not (tmp_path / "m.txt").exists()
