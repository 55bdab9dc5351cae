"""``bonecad cohort``: every bone of a folder or a CSV manifest through the per-bone job, on Dask.

source folder | manifest.csv -> BoneSource per bone -> cohort_job on a worker -> BoneRecord
    -> journal OUT/.bones/<id>.json (+ <id>.npy), as each bone finishes
    -> OUT/cohort.csv, OUT/cohort.json, OUT/points/<id>.npy, OUT/surface/<id>.npz, when every bone has ended

The job never raises for a bone's own failure: a bad input is recorded as
"bad input" (exit class 2) with its message, any other error as "failed"
(exit class 1) with its type, message and traceback; the rest of the cohort
goes on. A bone that hangs past ``[cohort] timeout_s`` is marked failed and its
worker restarted; a bone whose worker dies is run again on another (see
``run/cluster.py``).

The journal makes an interrupted run (Ctrl-C, SIGTERM, a kill) resume where
it stopped: each bone's record is committed atomically by this process as its
result arrives, with the hash of the settings (all but ``[cohort]``, and
bonecad's version) and the source's size and modification time. A rerun into
the same folder takes a done or bad-input bone from the journal when all
three match, and runs the others again (failed ones, a changed file, changed
settings). The table, the points and the surfaces are written all or nothing at the end.
"""
from __future__ import annotations

import csv
import hashlib
import json
import logging
import os
import platform
import re
import socket
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np

from bonecad._version import __version__
from bonecad.anatomy.frame import AnatomicalFrame
from bonecad.anatomy.morphometry import measure_tibia
from bonecad.errors import InputError
from bonecad.mesh.intake import MESH_SUFFIXES, Units
from bonecad.run.bones import bone_frame, bone_settings
from bonecad.run.cluster import DaskExecutor
from bonecad.run.shapes import fit_figures, load_surface, save_surface, template_fit_bone
from bonecad.run.executor import Executor, huge_pages
from bonecad.run.pipeline import VOLUME_SUFFIXES, load_input
from bonecad.settings import Settings
from bonecad.staging import staged_file, staged_output

log = logging.getLogger(__name__)

Status = Literal["done", "bad input", "failed"]
#: the exit status each status maps to (as the single-bone commands' exit codes)
EXIT_CLASS: Mapping[str, int] = {"done": 0, "bad input": 2, "failed": 1}
#: seconds between looks at the running bones (for the timeout) while waiting for results
_POLL_S = 1.0
#: volume files a folder may hold (DICOM slices belong in a DICOM sub-folder, one per volume)
_VOLUME_FILES = tuple(s for s in VOLUME_SUFFIXES if s not in (".dcm", ".ima"))
_ID = re.compile(r"^[\w\-][\w.\-]*$")
_JOURNAL = ".bones"


@dataclass(frozen=True)
class BoneSource:
    """One bone of the cohort: its id (a file name), its mesh file or CT volume, and what a manifest says of it
    (units of a mesh; side, checked against the anatomy; any other columns, carried into the table)."""

    bone_id: str
    path: Path
    units: Units = "auto"
    side: str | None = None
    extra: Mapping[str, str] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class BoneRecord:
    """What the cohort keeps of one bone: status, error, parameters (mm, degrees), fit figures, the template's
    control points ((n, 3) mm, bone coordinates) and the surface it was fitted to (points (m, 3) mm in bone
    coordinates and their area weights (m,) mm^2: ``template.surface_targets``) when fitted, CPU and wall seconds,
    and the worker (host:pid)."""

    bone_id: str
    source: str
    status: Status
    error: str = ""
    detail: str = ""  # the traceback of a failure
    side: str = ""
    parameters: Mapping[str, float] = field(default_factory=dict)
    figures: Mapping[str, float] = field(default_factory=dict)
    control_points: np.ndarray | None = None
    surface: tuple[np.ndarray, np.ndarray] | None = None
    cpu_s: float = 0.0
    wall_s: float = 0.0
    worker: str = ""

    @property
    def exit_class(self) -> int:
        return EXIT_CLASS[self.status]

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready, without the control points and the surface (they go to .npy and .npz files)."""
        return {"id": self.bone_id, "path": self.source, "status": self.status, "exit_class": self.exit_class,
                "error": self.error, "detail": self.detail, "side": self.side,
                "parameters": dict(self.parameters), "figures": dict(self.figures),
                "control_points": None if self.control_points is None else len(self.control_points),
                "cpu_s": self.cpu_s, "wall_s": self.wall_s, "worker": self.worker}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], control_points: np.ndarray | None,
                  surface: tuple[np.ndarray, np.ndarray] | None = None) -> BoneRecord:
        return cls(bone_id=d["id"], source=d["path"], status=d["status"], error=d["error"], detail=d["detail"],
                   side=d["side"], parameters=d["parameters"], figures=d["figures"], control_points=control_points,
                   surface=surface, cpu_s=d["cpu_s"], wall_s=d["wall_s"], worker=d["worker"])


def frame_parameters(frame: AnatomicalFrame) -> dict[str, float]:
    """The anatomical frame's own figures beside ``bonecad measure``'s (mm): the plateau ellipse's semi-axes,
    the bone's extent along the axis, the region boundaries above the plafond."""
    return {"plateau_semi_major_mm": float(frame.plateau.semi_axes_mm[0]),
            "plateau_semi_minor_mm": float(frame.plateau.semi_axes_mm[1]),
            "axial_extent_mm": float(frame.bone_extent_mm[1] - frame.bone_extent_mm[0]),
            "distal_boundary_mm": float(frame.distal_boundary_mm),
            "proximal_boundary_mm": float(frame.proximal_boundary_mm)}


def frame_figures(frame: AnatomicalFrame) -> dict[str, float]:
    """How well the frame's fits hold (mm): the plateau ellipse's RMS residual."""
    return {"fit_plateau_ellipse_rms_mm": float(frame.plateau.rms_residual_mm)}


def _bone_results(source: BoneSource, settings: Settings
                  ) -> tuple[str, dict[str, float], dict[str, float], np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """One bone's side, parameters, fit figures, template control points and the surface they were fitted to."""
    bone = load_input(source.path, settings, units=source.units)
    settings = bone_settings(bone, settings)
    frame = bone_frame(bone, settings)
    if frame.bone != "tibia":
        raise InputError(f"a cohort of tibias (measure, template); this is a {frame.bone}", source.path)
    if source.side is not None and source.side != frame.side:
        raise InputError(f"the manifest says a {source.side} tibia; the anatomy (medial malleolus, tuberosity) "
                         f"says {frame.side}", source.path)
    measured = measure_tibia(bone, frame, settings.morphometry).values()
    fit, surface_points, surface_weights = template_fit_bone(bone, settings, frame=frame)
    return frame.side, {**measured, **frame_parameters(frame)}, {**frame_figures(frame), **fit_figures(fit)}, \
        fit.control_points, (surface_points, surface_weights)


def cohort_job(source: BoneSource, settings: Settings) -> BoneRecord:
    """One bone on a worker: intake (or CT segmentation), anatomical frame and its figures. Never raises for the
    bone's own failure: an ``InputError`` is recorded as "bad input" with its message, any other error as
    "failed" with its type, message and traceback."""
    from threadpoolctl import threadpool_limits

    cpu, wall = time.process_time(), time.perf_counter()
    status: Status = "done"
    error = detail = side = ""
    parameters: dict[str, float] = {}
    figures: dict[str, float] = {}
    points = surface = None
    try:
        with threadpool_limits(limits=1, user_api="blas"), huge_pages(settings.pipeline.huge_pages):
            side, parameters, figures, points, surface = _bone_results(source, settings)
    except InputError as exc:
        status, error = "bad input", str(exc)
    except Exception as exc:  # recorded, not raised: the rest of the cohort goes on
        status, error, detail = "failed", f"{type(exc).__name__}: {exc}", traceback.format_exc()
    return BoneRecord(bone_id=source.bone_id, source=str(source.path), status=status, error=error, detail=detail,
                      side=side, parameters=parameters, figures=figures, control_points=points, surface=surface,
                      cpu_s=round(time.process_time() - cpu, 3), wall_s=round(time.perf_counter() - wall, 3),
                      worker=f"{socket.gethostname()}:{os.getpid()}")


# --- the cohort's bones ----------------------------------------------------------------------------------------

def _stem(path: Path) -> str:
    name = path.name
    for suffix in (".nii.gz", *MESH_SUFFIXES, *VOLUME_SUFFIXES):
        if name.lower().endswith(suffix):
            return name[: -len(suffix)]
    return name


def _safe_id(text: str) -> str:
    return re.sub(r"[^\w.\-]", "_", text).lstrip(".") or "bone"


def cohort_sources(path: str | Path, *, exclude: str | Path | None = None) -> list[BoneSource]:
    """The bones of a folder (every mesh file, volume file and DICOM sub-folder in it; hidden names and
    ``exclude``, the output folder, left out) or of a CSV manifest (see ``manifest_sources``), sorted by id."""
    path = Path(os.path.abspath(path))  # a bone's path is its journal's key: the same however it is named
    if path.is_file() and path.suffix.lower() == ".csv":
        return manifest_sources(path)
    if not path.is_dir():
        raise InputError("not a folder of bones or a CSV manifest" if path.exists() else "no such folder or file",
                         path)
    skip = Path(exclude).resolve() if exclude is not None else None
    entries = sorted(p for p in path.iterdir() if not p.name.startswith(".") and p.resolve() != skip)
    inputs = [p for p in entries if p.is_dir() or p.name.lower().endswith(MESH_SUFFIXES + _VOLUME_FILES)]
    ignored = [p.name for p in entries if p not in inputs]
    if ignored:
        log.info("not bones (neither a mesh nor a CT volume), left out: %s", ", ".join(ignored))
    if not inputs:
        raise InputError(f"no bone in the folder: no mesh file ({', '.join(MESH_SUFFIXES)}), volume file "
                         f"({', '.join(_VOLUME_FILES)}) or DICOM sub-folder", path)
    stems = [_safe_id(_stem(p)) for p in inputs]
    ids = [s if stems.count(s) == 1 else _safe_id(p.name) for s, p in zip(stems, inputs)]
    return sorted((BoneSource(i, p) for i, p in zip(ids, inputs)), key=lambda s: s.bone_id)


def manifest_sources(manifest: str | Path) -> list[BoneSource]:
    """The bones of a CSV manifest: a ``path`` column (relative to the manifest's folder), optional ``id``
    (default: the file name without its suffix), ``side`` (left/right, checked against the anatomy), ``units``
    (auto/mm/cm/m, of a mesh); other columns are carried into the cohort table."""
    manifest = Path(os.path.abspath(manifest))
    try:
        with manifest.open(newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            rows = list(reader)
            columns = [c.strip() for c in reader.fieldnames or []]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"cannot read the manifest ({exc})", manifest) from None
    if "path" not in columns:
        raise InputError(f"the manifest has no 'path' column (columns: {columns})", manifest)
    sources: list[BoneSource] = []
    seen: dict[str, int] = {}
    for line, row in enumerate(rows, start=2):
        row = {(k or "").strip(): (v or "").strip() for k, v in row.items()}
        if not row["path"]:
            raise InputError(f"line {line}: empty path", manifest)
        path = Path(row["path"]).expanduser()
        path = Path(os.path.abspath(manifest.parent / path))
        bone_id = row.get("id") or _safe_id(_stem(path))
        if not _ID.match(bone_id):
            raise InputError(f"line {line}: id {bone_id!r} is not a file name (letters, digits, '.', '_', '-')",
                             manifest)
        if bone_id in seen:
            raise InputError(f"line {line}: id {bone_id!r} is already on line {seen[bone_id]}", manifest)
        seen[bone_id] = line
        side, units = row.get("side") or None, row.get("units") or "auto"
        if side not in (None, "left", "right"):
            raise InputError(f"line {line}: side must be left or right, got {side!r}", manifest)
        if units not in ("auto", "mm", "cm", "m"):
            raise InputError(f"line {line}: units must be auto, mm, cm or m, got {units!r}", manifest)
        extra = {k: v for k, v in row.items() if k not in ("path", "id", "side", "units") and k}
        sources.append(BoneSource(bone_id, path, cast(Units, units), side, extra))
    if not sources:
        raise InputError("the manifest lists no bone", manifest)
    return sorted(sources, key=lambda s: s.bone_id)


# --- the journal -----------------------------------------------------------------------------------------------

def settings_hash(settings: Settings) -> str:
    """What makes a journalled bone reusable: every section but ``[cohort]`` (workers, timeouts), and the
    version of bonecad."""
    tree = {k: v for k, v in settings.to_dict().items() if k != "cohort"}
    text = json.dumps({"bonecad": __version__, "settings": tree}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _fingerprint(path: Path) -> list[int]:
    """Size (bytes), modification time (ns) and file count of a source (a DICOM folder: of its files)."""
    files = [p for p in path.rglob("*") if p.is_file()] if path.is_dir() else [path] if path.exists() else []
    stats = [p.stat() for p in files]
    return [sum(s.st_size for s in stats), max((s.st_mtime_ns for s in stats), default=0), len(stats)]


class Journal:
    """One record per finished bone in ``OUT/.bones``, committed atomically (the points and the surface first,
    then the record)."""

    def __init__(self, out_dir: Path, settings_hash: str):
        self.folder = out_dir / _JOURNAL
        self.settings_hash = settings_hash

    def finished(self, source: BoneSource) -> BoneRecord | None:
        """The bone's journalled record if it is final (done or bad input) for these settings and this source."""
        try:
            entry = json.loads((self.folder / f"{source.bone_id}.json").read_text())
        except (OSError, ValueError):
            return None
        record = entry["record"]
        if (entry["settings_hash"] != self.settings_hash or entry["source"] != _fingerprint(source.path)
                or record["path"] != str(source.path) or record["status"] not in ("done", "bad input")):
            return None
        points = surface = None
        if record["control_points"] is not None:
            try:
                points = np.load(self.folder / f"{source.bone_id}.npy")
                surface = load_surface(self.folder / f"{source.bone_id}.npz")
            except (OSError, ValueError, KeyError):
                return None
        return BoneRecord.from_dict(record, points, surface)

    def commit(self, source: BoneSource, record: BoneRecord) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        if record.control_points is not None:
            with staged_file(self.folder / f"{source.bone_id}.npy") as tmp:
                np.save(tmp, record.control_points)
        if record.surface is not None:
            with staged_file(self.folder / f"{source.bone_id}.npz") as tmp:
                save_surface(tmp, record.surface)
        entry = {"settings_hash": self.settings_hash, "source": _fingerprint(source.path),
                 "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "record": record.as_dict()}
        with staged_file(self.folder / f"{source.bone_id}.json") as tmp:
            tmp.write_text(json.dumps(entry, indent=1))


# --- the run ---------------------------------------------------------------------------------------------------

#: called once before the first bone with (bones ended, bones in all, None), then after each bone with its record
CohortProgress = Callable[[int, int, "BoneRecord | None"], None]


@dataclass(frozen=True, eq=False)
class CohortResult:
    """A cohort run: every bone's record (sorted by id), how many came from the journal, the output folder, wall s."""

    records: tuple[BoneRecord, ...]
    resumed: int
    out_dir: Path
    wall_s: float

    def count(self, status: Status) -> int:
        return sum(r.status == status for r in self.records)

    @property
    def failures(self) -> tuple[BoneRecord, ...]:
        return tuple(r for r in self.records if r.status != "done")

    @property
    def exit_status(self) -> int:
        """0 when every bone is done, else the worst exit class (1 failed over 2 bad input)."""
        classes = {r.exit_class for r in self.records} - {0}
        return 1 if 1 in classes else 2 if classes else 0


def _failed(source: BoneSource, error: str) -> BoneRecord:
    return BoneRecord(bone_id=source.bone_id, source=str(source.path), status="failed", error=error)


def run_cohort(source: str | Path, out_dir: str | Path, settings: Settings, *, scheduler: str | None = None,
               job: Callable[[BoneSource, Settings], BoneRecord] = cohort_job,
               progress: CohortProgress | None = None) -> CohortResult:
    """Run ``job`` (default ``cohort_job``) on every bone of a folder or manifest on a Dask cluster (local:
    ``[cohort] workers`` processes; or the existing scheduler at ``scheduler``), resuming from ``out_dir``'s
    journal, and write the cohort table, its JSON and the points into ``out_dir``."""
    started = time.perf_counter()
    out_dir = Path(out_dir)
    sources = cohort_sources(source, exclude=out_dir)
    journal = Journal(out_dir, settings_hash(settings))
    records = {s.bone_id: r for s in sources if (r := journal.finished(s)) is not None}
    resumed = len(records)
    todo = [s for s in sources if s.bone_id not in records]
    log.info("%d bones: %d from the journal of %s, %d to run", len(sources), resumed, out_dir, len(todo))
    if progress is not None:
        progress(resumed, len(sources), None)

    def finish(s: BoneSource, record: BoneRecord) -> None:
        journal.commit(s, record)
        records[s.bone_id] = record
        log.info("%s: %s%s (%.1f s CPU)", s.bone_id, record.status, f": {record.error}" if record.error else "",
                 record.cpu_s)
        if progress is not None:
            progress(len(records), len(sources), record)

    if todo:
        cohort = settings.cohort
        with DaskExecutor(workers=cohort.workers, scheduler=scheduler,
                          retries=cohort.retries, allowed_failures=cohort.allowed_failures) as ex:
            _run_jobs(ex, todo, settings, job, finish)
    ordered = tuple(records[s.bone_id] for s in sources)
    write_cohort(out_dir, sources, ordered, settings, source=Path(source))
    return CohortResult(ordered, resumed, out_dir, round(time.perf_counter() - started, 3))


def _run_jobs(ex: DaskExecutor, todo: Sequence[BoneSource], settings: Settings,
              job: Callable[[BoneSource, Settings], BoneRecord], finish: Callable[[BoneSource, BoneRecord], None]
              ) -> None:
    """Submit every bone, then record each as it ends; a bone running past the timeout is stopped and failed."""
    timeout = settings.cohort.timeout_s
    pending = {j.key: (j, s) for j, s in ((ex.submit(job, s, settings), s) for s in todo)}
    while pending:
        for j in ex.done([j for j, _ in pending.values()], _POLL_S):
            _, s = pending.pop(j.key)
            try:
                record = j.result()
            except Exception as exc:  # the job itself never raises: its worker died, or its result was lost
                record = _failed(s, f"{type(exc).__name__}: {exc}")
            finish(s, record)
        for key, running in ex.running().items():
            if key in pending and running.seconds > timeout:
                j, s = pending.pop(key)
                ex.stop(j, running.worker)
                finish(s, _failed(s, f"still running after {running.seconds:.0f} s on {running.worker} "
                                     f"([cohort] timeout_s = {timeout:g}); stopped"))


# --- the output ------------------------------------------------------------------------------------------------

def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {"bonecad": __version__, "python": platform.python_version()}
    for name in ("numpy", "scipy", "trimesh", "dask", "distributed"):
        try:
            out[name] = version(name)
        except PackageNotFoundError:  # pragma: no cover - metadata missing in odd installs
            out[name] = "unknown"
    return out


def _columns(records: Sequence[BoneRecord], attr: str) -> list[str]:
    names: dict[str, None] = {}
    for r in records:
        names.update(dict.fromkeys(getattr(r, attr)))
    return list(names)


def write_cohort(out_dir: Path, sources: Sequence[BoneSource], records: Sequence[BoneRecord], settings: Settings,
                 *, source: Path) -> None:
    """cohort.csv (one row per bone), cohort.json (the same, the failures, the settings and versions),
    points/<id>.npy and surface/<id>.npz (what ``shape-model build`` measures the generalisation against), all or
    nothing."""
    parameters, figures = _columns(records, "parameters"), _columns(records, "figures")
    extra = list(dict.fromkeys(k for s in sources for k in s.extra))
    with staged_output(out_dir) as stage:
        with (stage / "cohort.csv").open("w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["id", "path", "status", "error", *extra, "side", *parameters, *figures, "cpu_s"])
            for s, r in zip(sources, records):
                writer.writerow([r.bone_id, r.source, r.status, r.error, *(s.extra.get(k, "") for k in extra),
                                 r.side, *(_cell(r.parameters.get(k)) for k in parameters),
                                 *(_cell(r.figures.get(k)) for k in figures), r.cpu_s])
        points = {r.bone_id: r.control_points for r in records if r.control_points is not None}
        if points:
            (stage / "points").mkdir()
            for bone_id, array in points.items():
                np.save(stage / "points" / f"{bone_id}.npy", array)
        surfaces = {r.bone_id: r.surface for r in records if r.surface is not None}
        if surfaces:
            (stage / "surface").mkdir()
            for bone_id, surface in surfaces.items():
                save_surface(stage / "surface" / f"{bone_id}.npz", surface)
        counts = {status: sum(r.status == status for r in records) for status in EXIT_CLASS}
        doc = {"input": str(source), "bones": len(records), **{k.replace(" ", "_"): v for k, v in counts.items()},
               "cpu_s": round(sum(r.cpu_s for r in records), 3), "settings_hash": settings_hash(settings),
               "versions": _versions(), "settings": settings.to_dict(),
               "records": [{**r.as_dict(), **({"manifest": dict(s.extra)} if s.extra else {}),
                            "points": f"points/{r.bone_id}.npy" if r.control_points is not None else None,
                            "surface": f"surface/{r.bone_id}.npz" if r.surface is not None else None}
                           for s, r in zip(sources, records)],
               "failures": [{"id": r.bone_id, "path": r.source, "status": r.status, "error": r.error}
                            for r in records if r.status != "done"]}
        (stage / "cohort.json").write_text(json.dumps(doc, indent=1))


def _cell(value: float | None) -> str:
    return "" if value is None else f"{value:.6g}"


# --- a synthetic cohort ----------------------------------------------------------------------------------------

def _write_phantom(params: Any, path: Path, settings: Settings) -> Path:
    from bonecad.imaging.phantom_tibia import phantom_tibia

    bone = phantom_tibia(params, settings=settings.mesh, plausible=settings.units)
    with staged_file(path) as tmp:
        bone.to_trimesh().export(tmp, file_type="stl")
    return path


def write_phantom_cohort(folder: str | Path, count: int, settings: Settings, executor: Executor, *,
                         seed: int = 0, voxel_mm: float = 1.0) -> list[Path]:
    """``count`` phantom tibias of varied parameters (``varied_parameters``, seeded; marching cubes at
    ``voxel_mm``) as STL files ``phantom_000.stl``... in ``folder``, made on ``executor``; files already there
    are kept."""
    from bonecad.imaging.phantom_tibia import varied_parameters

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = [folder / f"phantom_{i:03d}.stl" for i in range(count)]
    jobs = [executor.submit(_write_phantom, replace(p, voxel_mm=voxel_mm), path, settings)
            for p, path in zip(varied_parameters(count, seed=seed), paths) if not path.exists()]
    for j in jobs:
        j.result()
    return paths

