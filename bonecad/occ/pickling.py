"""Models that cross between processes: their OpenCascade solid pickled as the binary B-rep.

OCP is imported only when a model is actually pickled, so a stage module can
use this mixin without paying for OpenCascade at import time.
"""
from __future__ import annotations


class ShapePickling:
    """Mixin of a frozen dataclass with fields ``shape`` (TopoDS_Shape) and ``face_names``
    ((name, TopoDS_Face) pairs): it pickles them as OpenCascade's binary B-rep (exact)."""

    def __getstate__(self) -> dict:
        from bonecad.occ.brep import pickle_named_shape

        state = dict(self.__dict__)
        state["shape"], state["face_names"] = pickle_named_shape(state["shape"], state["face_names"])
        return state

    def __setstate__(self, state: dict) -> None:
        from bonecad.occ.brep import unpickle_named_shape

        state = dict(state)
        state["shape"], state["face_names"] = unpickle_named_shape(state["shape"], state["face_names"])
        for key, value in state.items():
            object.__setattr__(self, key, value)
