"""cadquery interop: bonecad shapes are build123d/OCP shapes, so cadquery wraps the same TopoDS objects."""
from __future__ import annotations

from bonecad.errors import BonecadError


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
