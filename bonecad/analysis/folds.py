"""Folds: elements of a model's faces whose normal reverses (``splines.folds``).

The deviation from the mesh to the model does not see a fold (every mesh point
still has a close model point); the deviation from the model to the mesh does,
and this check names the elements. Every face of the solid is read exactly
(``occ.read_faces``) and split at its knots into polynomial elements (a
T-spline's Bezier elements as exported, or a NURBS face's knot spans), each
sampled on a ``samples x samples`` grid of its parameter rectangle. A face is
C1 or smoother inside, so a fold anywhere shows inside some element.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bonecad.splines.folds import FOLD_SAMPLES, FOLD_TURN_DEG, element_grid, largest_turn_deg
from bonecad.splines.surface import BSplineSurface


@dataclass(frozen=True)
class FoldCheck:
    """Elements checked and those whose normal reverses; ``where`` lists each reversed element as
    (face name, centre x, y, z in mm, the largest normal turn between neighbouring samples in degrees)."""

    elements: int
    reversed_elements: int
    where: tuple[tuple[str, float, float, float, float], ...] = ()

    def to_dict(self) -> dict:
        return {"elements": self.elements, "reversed_elements": self.reversed_elements,
                "where": [{"face": f, "centre_mm": [round(x, 3), round(y, 3), round(z, 3)],
                           "largest_turn_deg": round(t, 1)} for f, x, y, z, t in self.where]}


def _edges(knots: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """The distinct knot values within [lo, hi], the ends included: element edges of one direction."""
    tol = 1e-12 * max(1.0, abs(hi - lo))
    inside = knots[(knots > lo + tol) & (knots < hi - tol)]
    return np.unique(np.concatenate([[lo], inside, [hi]]))


def surface_folds(surface: BSplineSurface, name: str = "", *, samples: int = FOLD_SAMPLES) -> FoldCheck:
    """The elements of one surface (over its ``bounds``) and those whose normal reverses (module doc)."""
    u0, u1, v0, v1 = (float(b) for b in surface.bounds)
    eu, ev = _edges(surface.knots_u, u0, u1), _edges(surface.knots_v, v0, v1)
    gu = element_grid(eu[:-1], eu[1:], samples)  # (Eu, n)
    gv = element_grid(ev[:-1], ev[1:], samples)  # (Ev, n)
    nu, nv = len(gu), len(gv)
    uu = np.broadcast_to(gu[:, None, :, None], (nu, nv, samples, samples))
    vv = np.broadcast_to(gv[None, :, None, :], (nu, nv, samples, samples))
    sample = surface.evaluate(uu.ravel(), vv.ravel(), order=1)
    shape = (nu * nv, samples, samples, 3)
    turn = largest_turn_deg(sample.du.reshape(shape), sample.dv.reshape(shape))
    folded = np.nonzero(turn > FOLD_TURN_DEG)[0]
    centres = sample.points.reshape(shape)[folded, samples // 2, samples // 2]
    where = tuple((name, float(x), float(y), float(z), float(turn[k])) for k, (x, y, z) in zip(folded, centres))
    return FoldCheck(int(nu * nv), len(folded), where)


def shape_folds(shape, face_names=(), *, samples: int = FOLD_SAMPLES) -> FoldCheck:
    """The fold check of every face of an OpenCascade solid (module doc), each named as in ``face_names``
    ((name, face) pairs, as the models give them). The faces' orientation does not matter: a fold turns
    neighbouring normals against each other whichever way they point."""
    from bonecad.occ.brep import faces, names_in_order
    from bonecad.occ.read_faces import face_spline_surface

    shape_faces = faces(shape)
    names = names_in_order(shape_faces, face_names) if face_names else [f"face {i}" for i in range(len(shape_faces))]
    checks = []
    for name, face in zip(names, shape_faces):
        surface, _ = face_spline_surface(face)
        if surface is None:
            raise ValueError(f"face {name} of the model could not be read as a B-spline surface")
        checks.append(surface_folds(surface, name, samples=samples))
    return FoldCheck(sum(c.elements for c in checks), sum(c.reversed_elements for c in checks),
                     tuple(w for c in checks for w in c.where))
