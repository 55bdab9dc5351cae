"""build123d and cadquery interop: both wrap the same OCP TopoDS objects as bonecad's shapes."""
from __future__ import annotations

from bonecad.errors import BonecadError


def to_build123d(shape):
    """A build123d Solid wrapping the OCP TopoDS_Solid ``shape``, no copy."""
    from build123d import Solid

    return Solid(shape)


def to_cadquery(shape):
    """A cadquery Workplane holding ``shape`` (a build123d shape or an OCP TopoDS_Shape), no copy.

    Needs the optional extra: ``pip install 'bonecad[cadquery]'`` (cadquery on the same OCP version).
    """
    try:
        import cadquery
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise BonecadError("cadquery is not installed: pip install 'bonecad[cadquery]'") from exc
    wrapped = getattr(shape, "wrapped", shape)
    return cadquery.Workplane("XY").add(cadquery.Shape.cast(wrapped))
