"""`bonecad reconstruct`: the output contract on the phantom (the session's ``phantom_run``; the NURBS model's files
here, the T-spline's with its stage)."""
from __future__ import annotations

import json
import threading

import pytest

from bonecad.anatomy.morphometry import PARAMETER_NAMES
from bonecad.run.cli import main

CONTRACT = {"nurbs.step", "nurbs.iges", "curves.step", "curves.iges", "curves.json", "frame.json", "report.json",
            "report.html", "nurbs_deviation.png", "histograms.png", "nurbs_zebra.png", "curves.png"}


def test_output_contract(phantom_run):
    assert CONTRACT <= {p.name for p in phantom_run.iterdir()}
    assert not any(p.name.startswith(".") for p in phantom_run.parent.iterdir())  # no staging left


def test_report_json(phantom_run):
    report = json.loads((phantom_run / "report.json").read_text())
    assert report["schema"] == "bonecad.report/1"
    assert report["input"]["side"] == "right"
    nurbs = report["models"]["nurbs"]
    assert nurbs["info"]["faces"] == 5 and nurbs["info"]["control_points"] > 1000
    stats = nurbs["deviation"]["mesh_to_cad"]["stats"]
    assert stats["rms_mm"] < 0.2
    shares = nurbs["deviation"]["mesh_to_cad"]["histogram"]["shares"]
    assert sum(shares) == pytest.approx(1.0, abs=1e-9)
    assert set(nurbs["deviation"]["mesh_to_cad"]["regions"]) == {"distal", "shaft", "proximal"}
    assert set(report["timings_s"]) >= {"input", "anatomical frame", "contour curves", "NURBS model", "morphometry"}
    assert list(report["morphometry"]) == list(PARAMETER_NAMES)  # `bonecad measure`'s values, cheaply


def test_nurbs_step_is_one_closed_valid_solid(phantom_run, phantom):
    from OCP.BRepCheck import BRepCheck_Analyzer
    from OCP.BRepGProp import BRepGProp
    from OCP.GProp import GProp_GProps
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.STEPControl import STEPControl_Reader
    from OCP.TopAbs import TopAbs_SOLID
    from OCP.TopExp import TopExp_Explorer

    reader = STEPControl_Reader()
    assert reader.ReadFile(str(phantom_run / "nurbs.step")) == IFSelect_RetDone
    reader.TransferRoots()
    shape = reader.OneShape()
    explorer = TopExp_Explorer(shape, TopAbs_SOLID)
    solids = []
    while explorer.More():
        solids.append(explorer.Current())
        explorer.Next()
    assert len(solids) == 1
    assert BRepCheck_Analyzer(solids[0]).IsValid()
    props = GProp_GProps()
    BRepGProp.VolumeProperties_s(solids[0], props, 1e-6)
    mesh_volume = abs(phantom.to_trimesh().volume)
    assert abs(props.Mass() - mesh_volume) / mesh_volume < 0.01


def test_cad_files_carry_a_fixed_date(phantom_run):
    """STEP and IGES headers hold a fixed date, not the time of the run (the same input gives the same file)."""
    from bonecad.occ.brep import FIXED_TIMESTAMP

    iges_date = FIXED_TIMESTAMP.replace("-", "").replace("T", ".").replace(":", "")
    for path in sorted(phantom_run.glob("*.step")):
        assert f"FILE_NAME('{path.stem.replace('curves', 'bonecad_curves')}','{FIXED_TIMESTAMP}'" in path.read_text()
    for path in sorted(phantom_run.glob("*.iges")):
        global_section = "".join(line[:72] for line in path.read_text().splitlines() if line[72:73] == "G")
        assert global_section.count(f"15H{iges_date}") == 2  # the file's date and its last change


def test_bad_input_leaves_nothing(tmp_path, capsys):
    bad = tmp_path / "empty.stl"
    bad.write_bytes(b"")
    out = tmp_path / "out"
    assert main(["reconstruct", str(bad), "--out", str(out), "-q"]) == 2
    assert not out.exists()
    assert "empty" in capsys.readouterr().err


def test_an_error_in_the_frame_stage_exits_2_and_leaves_nothing(tmp_path, phantom, capsys):
    """The frame and the curves run in a child process: its error still ends the run cleanly."""
    mesh = tmp_path / "phantom.stl"
    phantom.to_trimesh().export(mesh)
    out = tmp_path / "out"
    assert main(["reconstruct", str(mesh), "--out", str(out), "--distal-boundary", "5000", "-q"]) == 2
    assert not out.exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "region boundaries" in err[0]


def test_background_jobs_change_nothing_but_time(tmp_path, phantom_run, monkeypatch):
    """The second core's jobs (bonecad.run.executor) give the same models and figures as one process:
    every file byte for byte (STEP, IGES, JSON, PNG), the report but for its timings. The session's
    ``phantom_run`` (background jobs, the default) against the same command in one process.

    And that process starts no Python thread: a Ctrl-C (KeyboardInterrupt) or a child's failure signal
    raised in the main thread while it joins a pool of Python threads frees the arrays they still write
    (scipy's cKDTree.query with ``workers=-1``: the CLI died of a segmentation fault, leaving its staging
    folder, when interrupted during the T-spline fit's first closest-point search)."""
    config = tmp_path / "one_process.toml"
    config.write_text("[pipeline]\nbackground_jobs = false\n")
    alone = tmp_path / "one_process"
    started = []
    start = threading.Thread.start

    def noted_start(thread: threading.Thread) -> None:
        started.append(thread.name)
        start(thread)

    monkeypatch.setattr(threading.Thread, "start", noted_start)
    assert main(["reconstruct", str(phantom_run.parent / "phantom.stl"), "--out", str(alone), "--config", str(config),
                 "-q"]) == 0
    monkeypatch.undo()
    assert not started, f"threads started in the run's process: {started}"
    reports = []
    for out in (phantom_run, alone):
        report = json.loads((out / "report.json").read_text())
        for model in report["models"].values():
            model["info"].pop("timings_s", None)
            model["deviation"].pop("timings_s", None)
        reports.append((report["models"], json.loads((out / "curves.json").read_text()),
                        sorted(p.name for p in out.iterdir())))
    assert reports[0] == reports[1]
    assert all(model["info"]["control_points"] > 0 for model in reports[0][0].values())
    for name in reports[0][2]:
        if not name.startswith("report."):
            assert (phantom_run / name).read_bytes() == (alone / name).read_bytes(), name
