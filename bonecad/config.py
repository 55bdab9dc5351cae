"""Defaults (angles, control-point counts, tolerances) loaded from ``data/defaults.toml``.

The figures live in the data file, not in code; a user file with the same
layout overrides any subset of them.
"""
from __future__ import annotations

import copy
import sys
from importlib import resources
from pathlib import Path
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from bonecad.errors import InputError

_DEFAULTS_CACHE: dict[str, Any] | None = None


def _read_defaults() -> dict[str, Any]:
    global _DEFAULTS_CACHE
    if _DEFAULTS_CACHE is None:
        text = resources.files("bonecad").joinpath("data/defaults.toml").read_text()
        _DEFAULTS_CACHE = tomllib.loads(text)
    return _DEFAULTS_CACHE


def _merge(base: dict[str, Any], override: dict[str, Any], where: str) -> None:
    for key, value in override.items():
        if key not in base:
            raise InputError(f"unknown setting '{where}{key}'")
        if isinstance(base[key], dict):
            if not isinstance(value, dict):
                raise InputError(f"setting '{where}{key}' must be a table")
            _merge(base[key], value, f"{where}{key}.")
        else:
            base[key] = value


def load_config(path: str | Path | None = None) -> dict[str, Any]:
    """The defaults, with the settings of the TOML file ``path`` (if given) laid over them."""
    config = copy.deepcopy(_read_defaults())
    if path is not None:
        try:
            override = tomllib.loads(Path(path).read_text())
        except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise InputError(f"cannot read configuration: {exc}", path) from exc
        try:
            _merge(config, override, "")
        except InputError as exc:
            raise InputError(exc.problem, path) from None
    return config
