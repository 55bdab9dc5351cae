"""bonecad's exceptions: one base, and a class per kind of failure.

``InputError`` (bad user input: file, units, anatomy) maps to exit status 2 in
the CLI; everything else is an internal failure (exit status 1).
"""
from __future__ import annotations


class BonecadError(Exception):
    """Base class of every error bonecad raises on purpose."""


class InputError(BonecadError, ValueError):
    """The input cannot be used: names the file (when there is one) and the problem."""

    def __init__(self, problem: str, path: object | None = None):
        self.problem = problem
        self.path = None if path is None else str(path)
        super().__init__(f"{self.path}: {problem}" if self.path else problem)


class FitError(BonecadError):
    """A curve or surface fit could not reach a usable result."""


class KernelError(BonecadError, RuntimeError):
    """An OpenCascade operation failed (IsDone() false, invalid shape, writer error)."""
