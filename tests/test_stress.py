"""A bounded, seeded sample of the stress suite (``benchmarks/stress.py``; generators in tests/stress_cases.py).

Every case must end in a frame or an InputError (exit 2): any other exception is an internal error (exit 1)
and fails with the case's id and seed, replayable with
``python benchmarks/stress.py --only CASE_ID --cases N --seed SEED --out DIR`` (N: the index in the id + 1).

The fast sample (42 mesh cases from the smaller meshes: ICL's tibia, LHDL's, the femurs; about 2-4 s each
on a loaded machine) runs each case's intake and frame in this process, as `bonecad reconstruct` starts. The
slow ones run whole reconstructions and whole-leg CTs with a bone in contact.
"""
from __future__ import annotations

import pytest

from bonecad.errors import InputError

from .conftest import DATA
from .stress_cases import MESH_KINDS, Case, build_case, make_cases

SEED = 7
#: meshes cheap enough for every commit (the 120-145 k triangle tibias and TLEM2's 169 k femur left out)
SMALL = [p.relative_to(DATA).as_posix() for folder in ("tibia", "femur", "femur_pairs")
         for p in sorted((DATA / folder).glob("*.stl")) if p.stat().st_size < 4_000_000]
FAST = make_cases(42, SEED, kinds=MESH_KINDS, sources=SMALL) if SMALL else []


def _replay(case: Case) -> str:
    index = case.seed - SEED * 100003
    return (f"case {case.case_id} (seed {case.seed}); replay: python benchmarks/stress.py --only {case.case_id} "
            f"--cases {index + 1} --seed {SEED} --kinds {','.join(MESH_KINDS)} --out DIR")


def _frame_or_input_error(case: Case, tmp_path):
    """The frame of the case's input (intake, then frame, as `reconstruct` starts) or the InputError it ends
    with; any other exception fails the test naming the case."""
    from bonecad.run.bones import bone_frame, bone_settings
    from bonecad.run.pipeline import load_input
    from bonecad.settings import Settings

    built = build_case(case, tmp_path)
    units = built.args[1] if built.args[:1] == ("--units",) else "auto"
    try:
        settings = Settings.load()
        bone = load_input(built.path, settings, units=units)
        return built, bone_frame(bone, bone_settings(bone, settings))
    except InputError as exc:
        return built, exc
    except Exception as exc:  # an internal error: exit 1
        pytest.fail(f"internal error ({type(exc).__name__}: {exc}) on {_replay(case)}")


@pytest.mark.skipif(not FAST, reason=f"bone meshes absent from {DATA}")
@pytest.mark.parametrize("case", FAST, ids=[c.case_id for c in FAST])
def test_a_stress_case_ends_in_a_frame_or_a_clear_input_error(case, tmp_path):
    built, result = _frame_or_input_error(case, tmp_path)
    if isinstance(result, InputError):
        assert "exit 2" in case.expect or str(result), _replay(case)
        assert result.path is not None, f"the error names no file: {result} ({_replay(case)})"
        return
    assert "model" in case.expect, f"a frame where exit 2 was expected: {_replay(case)}"
    if built.side is not None and hasattr(result, "side"):
        assert result.side == built.side, f"side {result.side}, not {built.side}: {_replay(case)}"


def test_the_sample_covers_every_mesh_kind_and_both_bones():
    if not FAST:
        pytest.skip(f"bone meshes absent from {DATA}")
    assert {c.kind for c in FAST} == set(MESH_KINDS)
    assert any("femur" in c.source for c in FAST) and any("tibia" in c.source for c in FAST)


def test_cases_are_the_same_for_the_same_seed():
    assert make_cases(30, 3) == make_cases(30, 3)
    assert make_cases(10, 3) == make_cases(30, 3)[:10]


@pytest.mark.slow
def test_a_talus_pressed_into_the_mortise_is_parted_from_the_tibia(tmp_path):
    """TLEM2's talus moved 0.5 mm into the plafond (a broad contact, no neck), whole leg at 0.8 x 0.8 x 1.0
    mm: the segmented tibia ends where the true one does (it reached 31 mm below it, the talus attached)."""
    from bonecad.imaging.segment import segment_bone
    from bonecad.imaging.volume import read_volume
    from bonecad.settings import Settings

    from .stress_cases import LEGS

    if not all((DATA / f).is_file() for f in LEGS["TLEM2"][:4]):
        pytest.skip("TLEM2's leg is absent")
    case = Case("contact-TLEM2-test", "contact", "TLEM2", 0,
                {"pixel_mm": 0.8, "slice_mm": 1.0, "bone": "talus", "gap_mm": -0.5})
    built = build_case(case, tmp_path)
    assert built.facts["gap_mm"] < -0.4 and built.facts["contact_mm2"] > 400.0  # a broad contact
    settings = Settings.load()
    bone = segment_bone(read_volume(built.path), settings=settings.imaging, mesh_settings=settings.mesh)
    assert abs(bone.vertices[:, 2].min() - built.truth_vertices[:, 2].min()) < 1.0
    assert any("broad contact" in r for r in bone.repairs)
    from .stress_cases import surface_deviation

    share, worst, _ = surface_deviation(built.truth_vertices, built.truth_faces, bone.vertices, bone.faces)
    assert share >= 0.985 and worst < 1.6  # TLEM2's own cleft: 1.57 mm at the true joint space


#: cases of the benchmark's run that ended in an internal error, kept until fixed (docs/guides/stress.md)
FOUND = [pytest.param(c, marks=pytest.mark.xfail(strict=True, reason="contour curves: the 30 degree half-plane "
                                                 "section meets the apex twice (open)"))
         for c in make_cases(47, 0) if c.case_id == "ct-ICL-46"]


@pytest.mark.slow
@pytest.mark.parametrize("case", [c for c in make_cases(9, SEED, kinds=MESH_KINDS, sources=SMALL)
                                  if c.kind in ("rigid", "mirror", "defects")] + FOUND if SMALL else [],
                         ids=lambda c: c.case_id)
def test_a_stress_case_reconstructs_within_its_bars(case, tmp_path):
    """Whole `bonecad reconstruct` runs of a few cases, judged as the benchmark judges them."""
    import sys

    from .conftest import ROOT

    sys.path.insert(0, str(ROOT))
    from benchmarks.stress import run_case

    row = run_case(case, str(tmp_path))
    assert row["exit"] != 1 and row["exit"] != "timeout", f"{row['verdict']}: {row.get('reason')} ({_replay(case)})"


def test_a_tibia_without_a_malleolus_is_an_input_error_naming_the_file(monkeypatch, phantom):
    """The anatomy's checks that fail on the input (no malleolus, no tuberosity, no flare) are exit 2, and the
    error names the bone's file: issue 48's "side is ill-defined" was an internal error (exit 1)."""
    from dataclasses import replace

    import numpy as np

    from bonecad.anatomy import frame
    from bonecad.settings import Settings

    ring = np.array([[np.cos(a), np.sin(a), 0.0] for a in np.linspace(0, 2 * np.pi, 36, endpoint=False)]) * 10
    points = np.vstack([ring, ring + [0, 0, 100.0]])  # its lowest part centred on the axis
    with pytest.raises(InputError, match="malleolus"):
        frame._medial_direction(points, np.zeros(3), np.array([0, 0, 1.0]), points[:, 2], np.array([0, 1.0, 0]))

    def no_malleolus(bone, **_):
        frame._medial_direction(points, np.zeros(3), np.array([0, 0, 1.0]), points[:, 2], np.array([0, 1.0, 0]))

    monkeypatch.setattr(frame, "_frame", no_malleolus)
    settings = Settings.load()
    with pytest.raises(InputError, match="malleolus") as info:
        frame.anatomical_frame(replace(phantom, source="leg.stl"), settings=settings.anatomy,
                               plausible=settings.units)
    assert info.value.path == "leg.stl"
