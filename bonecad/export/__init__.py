"""Exporters: the files written from stage results, found by (kind of result, format).

Each exporter is a function ``(result, out_dir) -> Path`` (the file it wrote) registered with
``@exporter(kind, format)``; ``export(kind, result, out_dir)`` runs every
format of a kind (or the ones named). A new format is one module that
registers its functions and is imported here (e.g. ``.tsm`` for "tspline").
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Iterable

ExportFn = Callable[[Any, Path], Path]

#: (kind, format) -> exporter, in registration order
EXPORTERS: dict[tuple[str, str], ExportFn] = {}


def exporter(kind: str, fmt: str) -> Callable[[ExportFn], ExportFn]:
    """Register ``fn`` as the writer of ``fmt`` files for results of ``kind``."""

    def register(fn: ExportFn) -> ExportFn:
        if (kind, fmt) in EXPORTERS:
            raise ValueError(f"two exporters of {fmt} for {kind}")
        EXPORTERS[(kind, fmt)] = fn
        return fn

    return register


def formats(kind: str) -> list[str]:
    """The formats registered for a kind of result."""
    _load()
    return [fmt for k, fmt in EXPORTERS if k == kind]


def export(kind: str, result: Any, out_dir: Path, only: Iterable[str] | None = None) -> dict[str, Path]:
    """Write ``result`` in every registered format of ``kind`` (or those in ``only``) into ``out_dir``;
    returns format -> file."""
    _load()
    wanted = formats(kind) if only is None else list(only)
    unknown = set(wanted) - set(formats(kind))
    if unknown:
        raise ValueError(f"no exporter of {sorted(unknown)} for {kind}; there are {formats(kind)}")
    return {fmt: EXPORTERS[(kind, fmt)](result, Path(out_dir)) for fmt in wanted}


def _load() -> None:
    """Import the modules that register exporters (OpenCascade only when a file is written)."""
    from bonecad.export import cad, documents, report  # noqa: F401
