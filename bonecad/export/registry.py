"""The registry of exporters: (kind of result, format) -> function writing one file.

Each exporter is a function ``(result, out_dir) -> Path`` (the file it wrote),
registered with ``@exporter(kind, format)`` in one of ``FORMAT_MODULES``;
``export(kind, result, out_dir)`` writes every format of a kind (or the ones
named). The format modules are imported on first use (OpenCascade only when a
CAD file is written). A new format is one module registering its functions,
named in ``FORMAT_MODULES``.
"""
from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any
from collections.abc import Callable, Iterable

ExportFn = Callable[[Any, Path], Path]

#: the modules that register exporters
FORMAT_MODULES = ("bonecad.export.cad", "bonecad.export.documents", "bonecad.export.meshes", "bonecad.export.report",
                  "bonecad.export.tsm", "bonecad.export.plate", "bonecad.export.fe", "bonecad.export.iga")

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
    for module in FORMAT_MODULES:
        importlib.import_module(module)
    return [fmt for k, fmt in EXPORTERS if k == kind]


def export(kind: str, result: Any, out_dir: Path, only: Iterable[str] | None = None) -> dict[str, Path]:
    """Write ``result`` in every registered format of ``kind`` (or those in ``only``) into ``out_dir``;
    returns format -> file."""
    known = formats(kind)
    wanted = known if only is None else list(only)
    unknown = set(wanted) - set(known)
    if unknown:
        raise ValueError(f"no exporter of {sorted(unknown)} for {kind}; there are {known}")
    return {fmt: EXPORTERS[(kind, fmt)](result, Path(out_dir)) for fmt in wanted}
