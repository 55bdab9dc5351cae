"""How a ``bonecad reconstruct`` run ends: on an error in any job, and when it is stopped by a signal.

Black-box: the CLI runs as a subprocess (``python -m bonecad.run.cli``), so these
tests hold whatever the runner's internals are. Every run writes into a folder
unique to the test; processes forked from the CLI share its command line, so
"a process of this run" is any process whose /proc/PID/cmdline holds that
folder (orphans are re-parented, so the parent pid says nothing). Every wait
has a hard timeout and every test kills what is left of its run, so the tests
never hang and never leave processes behind.

Requirements (issue 17): every error ends the run within seconds, exit 2 for
bad input and 1 for an internal failure, one clear line, no output folder; the
fused tibia-fibula mesh is refused so (exit 2 naming the fibula). SIGINT/SIGTERM/SIGKILL
of the CLI leave no bonecad process running 5 s later and no staging folder
after SIGINT/SIGTERM; a later run into the same --out removes one left by SIGKILL.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from .conftest import ROOT, TIBIA_DIR

pytestmark = pytest.mark.skipif(not Path("/proc/self/cmdline").exists(), reason="needs /proc (Linux)")

REAL_TIBIA = TIBIA_DIR / "LHDL_CT_tibia_no_fib_r.stl"  # a whole reconstruction takes ~10-20 s
ERROR_DEADLINE_S = 60.0  # an error must end the run well within this
REAP_S = 5.0  # after a signal, every process of the run must be gone within this
STAGE_DEADLINE_S = 120.0  # a loaded machine: the models stage is normally reached after ~6 s
RUN_DEADLINE_S = 180.0  # a whole run on REAL_TIBIA (normally 10-20 s)
MODEL_STAGE = "T-spline model ..."  # the stage line printed when the models are being built


# --- processes of one run --------------------------------------------------------------------------

def cli_env() -> dict:
    """The environment of the CLI subprocess: this checkout's bonecad first."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    env.pop("PYTHONINSPECT", None)
    return env


def cli(*args) -> list[str]:
    return [sys.executable, "-m", "bonecad.run.cli", *map(str, args)]


def run_processes(marker: Path) -> dict[int, str]:
    """pid -> "parent, state, kernel wait channel" of every live process (not a zombie) whose command line
    holds ``marker``."""
    needle = str(marker).encode()
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            if needle not in (entry / "cmdline").read_bytes():  # a zombie's cmdline is empty
                continue
            status = dict(line.split(":", 1) for line in (entry / "status").read_text().splitlines() if ":" in line)
            wchan = (entry / "wchan").read_text().strip() or "-"
        except (OSError, ValueError):
            continue  # gone meanwhile
        found[int(entry.name)] = f"parent {status['PPid'].strip()}, {status['State'].strip()}, kernel wait {wchan}"
    return found


def kill_run(marker: Path) -> None:
    """SIGKILL every process of this run (found by its unique folder), until none is left."""
    for _ in range(50):
        pids = run_processes(marker)
        if not pids:
            return
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        time.sleep(0.1)


def wait_gone(marker: Path, deadline: float) -> dict[int, str]:
    """Poll until no process of the run is alive or ``deadline`` (monotonic) passes; what is left."""
    while True:
        left = run_processes(marker)
        if not left or time.monotonic() >= deadline:
            return left
        time.sleep(0.1)


def describe(left: dict[int, str]) -> str:
    return "; ".join(f"pid {pid} ({state})" for pid, state in sorted(left.items()))


def staging_folders(out: Path) -> list[str]:
    """Staging folders of ``out`` (bonecad.staging: ``.NAME.staging-*`` beside it)."""
    return sorted(p.name for p in out.parent.glob(f".{out.name}.staging-*"))


def _sigint_as_in_a_terminal() -> None:
    """In the child, before exec: SIGINT at its default, as a terminal's foreground job has it, so Python
    turns Ctrl-C into KeyboardInterrupt. A test run started in the background by a non-interactive shell
    inherits SIGINT ignored, and would pass that on to the run."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class Run:
    """A ``bonecad`` subprocess whose stderr lines are collected as they come."""

    def __init__(self, args, cwd: Path):
        self.lines: list[str] = []
        self.proc = subprocess.Popen(args, cwd=cwd, env=cli_env(), stdin=subprocess.DEVNULL,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     start_new_session=True,  # its own process group: Ctrl-C is killpg
                                     preexec_fn=_sigint_as_in_a_terminal)
        self.stdout = ""
        self._seen = threading.Event()
        self._wanted = None
        self._err = threading.Thread(target=self._read_stderr, daemon=True)
        self._out = threading.Thread(target=self._read_stdout, daemon=True)
        self._err.start()
        self._out.start()

    def _read_stderr(self):
        for line in self.proc.stderr:
            self.lines.append(line.rstrip("\n"))
            if self._wanted is not None and self._wanted in line:
                self._seen.set()
        self._seen.set()  # end of stderr: the process has ended (or closed it)

    def _read_stdout(self):
        self.stdout = self.proc.stdout.read()

    def wait_for_line(self, text: str, timeout: float) -> bool:
        self._wanted = text
        if any(text in line for line in self.lines):
            return True
        self._seen.wait(timeout)
        return any(text in line for line in self.lines)

    def wait(self, timeout: float) -> int | None:
        """Exit status, or None if still running after ``timeout`` s."""
        try:
            code = self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None
        self._err.join(2.0)
        self._out.join(2.0)
        return code

    def stderr(self) -> str:
        return "\n".join(self.lines)


def check_one_line_error(code: int, stderr: str) -> list[str]:
    """Problems with an error exit: status 1 or 2 and one line, 'bonecad: error: ...' for 2 and
    'bonecad: internal error: ...' for 1 (the CLI's contract, as test_cli checks in-process)."""
    lines = stderr.strip().splitlines()
    problems = []
    if code not in (1, 2):
        problems.append(f"exit status {code}, expected 1 (internal failure) or 2 (bad input)")
    if len(lines) != 1:
        problems.append(f"stderr has {len(lines)} lines, expected one clear line: {stderr.strip()[-1500:]!r}")
    elif code in (1, 2):
        prefix = "bonecad: error: " if code == 2 else "bonecad: internal error: "
        if not lines[0].startswith(prefix) or len(lines[0]) <= len(prefix) + 10:
            problems.append(f"exit {code} with stderr {lines[0]!r}; "
                            f"expected a line starting {prefix!r} naming the problem")
    if "Traceback" in stderr:
        problems.append("a traceback on stderr")
    return problems


# --- the fused tibia-fibula mesh -------------------------------------------------------------------

def test_fused_mesh_is_one_body_joined_at_the_proximal_joint(fused_tibia_fibula):
    import trimesh

    path, fused = fused_tibia_fibula
    mesh = trimesh.load(path, force="mesh")
    bodies = mesh.split(only_watertight=False)
    assert len(bodies) == 1, f"{len(bodies)} bodies: tibia and fibula are not fused"
    assert mesh.is_watertight
    # the fibula is in it (volume of both bones, down to the lateral malleolus) ...
    assert abs(mesh.volume / fused.source_volume_mm3 - 1.0) < 0.03
    assert mesh.vertices[:, 2].min() < fused.fibula_bottom_z_mm + 1.5
    # ... and joined to the tibia at the proximal tibiofibular joint (0.17 mm apart in the source), 20-40 mm
    # below the plateau; the distal joint (1.5-2 mm apart) stays open at 1 mm voxels
    assert len(fused.contact_z_mm) > 0
    below_top = fused.tibia_top_z_mm - fused.contact_z_mm
    assert below_top.min() > 10.0 and below_top.max() < 50.0, below_top
    assert fused.seconds < 15.0, f"building the fused mesh took {fused.seconds:.1f} s"


def _config(tmp_path: Path, background: bool) -> list[str]:
    if background:
        return []
    path = tmp_path / "no_background.toml"
    path.write_text("[pipeline]\nbackground_jobs = false\n")
    return ["--config", path]


@pytest.mark.slow
@pytest.mark.parametrize("background", [True, False], ids=["background_jobs", "no_background_jobs"])
def test_fused_mesh_ends_with_one_line_and_no_output(fused_tibia_fibula, tmp_path, background):
    """The mesh intake refuses it: exit 2, one line naming the fibula, no output (it used to end in an
    internal error: 'the 150 degree half-plane section does not run from the apex to the region boundary')."""
    path, _ = fused_tibia_fibula
    out = tmp_path / "fused_out"
    run = Run(cli("reconstruct", path, "--out", out, "-q", *_config(tmp_path, background)), tmp_path)
    try:
        started = time.monotonic()
        code = run.wait(ERROR_DEADLINE_S)
        problems = []
        if code is None:
            problems.append(f"the run did not end within {ERROR_DEADLINE_S:.0f} s; its processes: "
                            f"{describe(run_processes(out))}; stderr so far: {run.stderr()[-800:]!r}")
            kill_run(out)
            run.wait(10.0)
        else:
            elapsed = time.monotonic() - started
            left = wait_gone(out, time.monotonic() + REAP_S)
            if left:
                problems.append(f"{len(left)} process(es) of the run still alive {REAP_S:.0f} s after it "
                                f"ended: {describe(left)}")
            problems += check_one_line_error(code, run.stderr())
            if code != 2 or "fused to its fibula" not in run.stderr():
                problems.append(f"exit {code} after {elapsed:.1f} s with {run.stderr()[-800:]!r}; expected exit 2 "
                                "naming the fibula")
            if out.exists():
                problems.append(f"the output folder {out} exists after a failed run")
            if staging_folders(out):
                problems.append(f"staging folder(s) left: {staging_folders(out)}")
        assert not problems, "\n".join(problems)
    finally:
        kill_run(out)
        if run.proc.poll() is None:
            run.proc.kill()
            run.proc.wait(10.0)


# --- signals ---------------------------------------------------------------------------------------

def _start_real_run(tmp_path: Path, out: Path) -> Run:
    if not REAL_TIBIA.is_file():
        pytest.skip(f"{REAL_TIBIA} is absent")
    return Run(cli("reconstruct", REAL_TIBIA, "--out", out), tmp_path)


def _signal_at_model_stage(run: Run, how: str) -> float:
    """Wait until the run builds its models (children at work), then signal it; the monotonic time sent."""
    if not run.wait_for_line(MODEL_STAGE, STAGE_DEADLINE_S):
        pytest.fail(f"the run never reached {MODEL_STAGE!r} (exit {run.proc.poll()}): {run.stderr()[-800:]!r}")
    time.sleep(0.5)  # inside the stage: the T-spline fit here, curve files and the NURBS model on the second core
    if run.proc.poll() is not None:
        pytest.fail(f"the run ended (exit {run.proc.returncode}) before it could be signalled")
    if how == "SIGINT-group":  # Ctrl-C in a terminal: the whole foreground process group
        os.killpg(run.proc.pid, signal.SIGINT)
    else:
        os.kill(run.proc.pid, getattr(signal, how))
    return time.monotonic()


@pytest.mark.slow
@pytest.mark.parametrize("how", ["SIGINT", "SIGINT-group", "SIGTERM"])
def test_signal_stops_every_process_and_removes_staging(tmp_path, how):
    """Today: SIGINT (to the CLI or, as Ctrl-C, to its group) passes; SIGTERM leaves a child (the curve
    files and NURBS job) orphaned and blocked on its pipe forever, and the staging folder."""
    out = tmp_path / "signalled_out"
    run = _start_real_run(tmp_path, out)
    try:
        sent = _signal_at_model_stage(run, how)
        code = run.wait(max(0.1, sent + REAP_S - time.monotonic()))
        left = wait_gone(out, sent + REAP_S)
        problems = []
        if code is None:
            problems.append(f"the CLI (pid {run.proc.pid}) still runs {REAP_S:.0f} s after {how}")
        elif code == 0:
            problems.append(f"exit status 0 after {how}")
        if left:
            problems.append(f"{len(left)} process(es) of the run still alive {REAP_S:.0f} s after {how}: "
                            f"{describe(left)}")
        if out.exists():
            problems.append(f"the output folder {out} exists after {how}")
        if staging_folders(out):
            problems.append(f"staging folder(s) left after {how}: {staging_folders(out)}, holding "
                            f"{[p.name for f in staging_folders(out) for p in (out.parent / f).iterdir()]}; "
                            f"the run said: {run.stderr()[-600:]!r}")
        assert not problems, "\n".join(problems)
    finally:
        kill_run(out)
        if run.proc.poll() is None:
            run.proc.kill()
            run.proc.wait(10.0)


@pytest.mark.slow
def test_sigkill_leaves_no_process_and_the_next_run_removes_the_staging_folder(tmp_path):
    """SIGKILL cannot be handled by the CLI itself: its children must notice (their parent is gone) and
    stop within seconds; the staging folder it leaves is removed by the next run into the same --out.
    Today: the child is orphaned and sleeps forever on its pipe; the next run succeeds but leaves the
    stale staging folder beside the output."""
    out = tmp_path / "killed_out"
    run = _start_real_run(tmp_path, out)
    rerun = None
    problems = []
    try:
        sent = _signal_at_model_stage(run, "SIGKILL")
        code = run.wait(REAP_S)
        left = wait_gone(out, sent + REAP_S)
        if code != -signal.SIGKILL:
            problems.append(f"the CLI's status after SIGKILL is {code}")
        if left:
            problems.append(f"{len(left)} process(es) of the run still alive {REAP_S:.0f} s after SIGKILL: "
                            f"{describe(left)}")
        if out.exists():
            problems.append(f"the output folder {out} exists after SIGKILL")
        stale = staging_folders(out)
        kill_run(out)  # whatever is left must not hold or write into the staging folder during the next run
        rerun = Run(cli("reconstruct", REAL_TIBIA, "--out", out, "--model", "nurbs", "-q"), tmp_path)
        code = rerun.wait(RUN_DEADLINE_S)
        if code is None:
            problems.append(f"the next run into {out} did not end within {RUN_DEADLINE_S:.0f} s")
        elif code != 0:
            problems.append(f"the next run into {out} failed (exit {code}): {rerun.stderr()[-800:]!r}")
        elif not (out / "report.json").is_file():
            problems.append(f"the next run into {out} wrote no report.json")
        if staging_folders(out):
            problems.append(f"staging folder(s) left after the next run: {staging_folders(out)} "
                            f"(left by SIGKILL: {stale})")
        assert not problems, "\n".join(problems)
    finally:
        kill_run(out)
        for r in (run, rerun):
            if r is not None and r.proc.poll() is None:
                r.proc.kill()
                r.proc.wait(10.0)
