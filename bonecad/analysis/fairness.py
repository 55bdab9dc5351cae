"""Fairness of a CAD model's surfaces: how much its curvature varies (issue 47; docs/guides/fairness.md).

The figure is the RMS over the surface of the gradient of the mean curvature H,

    F = sqrt( integral |grad_S H|^2 dA / integral dA )      (1/mm^2),

the curvature-variation energy of Moreton & Sequin (1992, "Functional optimization for fair surface
design", SIGGRAPH) in its mean-curvature form, normalised by the area so that bones of different sizes
and models of different face counts compare. A zebra figure (reflection lines; Hagen, Hahmann, Schreiber &
Nakajima 1992, "Surface interrogation algorithms") shows the normal's field; its stripes bend where the
curvature changes, so a surface whose curvature varies more has more wiggles and islands of stripes, and
ripple too small for any deviation bar (0.05 mm at 3 mm wavelength) raises F by orders of magnitude:
a ripple of amplitude a at wavelength L adds about a (2 pi / L)^3 / 2 to F, a bone's own shape a few
thousandths.

Computed from the exact surfaces, not the tessellation: every face is evaluated with its derivatives to
second order (``bonecad.splines.surface``) on a grid of about ``step_mm`` physical spacing; H is exact at
every grid node (first and second fundamental forms), and its surface gradient is taken by central
differences of those exact values along the grid, |grad H|^2 = (G H_u^2 - 2 F H_u H_v + E H_v^2) /
(E G - F^2), with the area element sqrt(E G - F^2) du dv. The differences resolve curvature variation at
wavelengths of 4 ``step_mm`` and longer. Degenerate spots (an apex cap's pole) count with no area.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from bonecad.splines.surface import BSplineSurface
from bonecad.splines.tspline import TSpline

#: A face whose fairness is measured: a B-spline surface (its ``bounds``) or a T-spline (its whole domain).
Surface = BSplineSurface | TSpline

#: Largest grid of one face (nodes); a face larger than this at ``step_mm`` is sampled more coarsely.
MAX_FACE_NODES = 1_500_000


@dataclass(frozen=True)
class Fairness:
    """The fairness figure of one model (module doc).

    curvature_variation : F, the RMS of |grad H| over the surface (1/mm^2; lower is fairer);
    regions : the same figure per region (name -> 1/mm^2); area_mm2 : the surface area measured (and per
    region in region_area_mm2); step_mm : the grid spacing; faces : faces evaluated.
    typical, typical_regions : the area-weighted median of |grad H| (1/mm^2), overall and per region: what
    half the surface exceeds. F is an energy, so one sharp spot the model follows (a foramen, a crease of
    the mesh) can hold most of it (LHDL's T-spline: 82 % in 0.1 % of its area); the median is not moved by
    such spots and tells ripple spread over the surface.
    """

    curvature_variation: float
    regions: dict[str, float] = field(default_factory=dict)
    area_mm2: float = 0.0
    region_area_mm2: dict[str, float] = field(default_factory=dict)
    step_mm: float = 0.0
    faces: int = 0
    typical: float = 0.0
    typical_regions: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "figure": "RMS of the gradient of mean curvature over the surface (curvature variation)",
            "units": "1/mm^2",
            "curvature_variation_per_mm2": round(self.curvature_variation, 6),
            "regions": {k: round(v, 6) for k, v in self.regions.items()},
            "typical_per_mm2": round(self.typical, 6),
            "typical_regions": {k: round(v, 6) for k, v in self.typical_regions.items()},
            "area_mm2": round(self.area_mm2, 1),
            "region_area_mm2": {k: round(v, 1) for k, v in self.region_area_mm2.items()},
            "step_mm": self.step_mm,
            "faces": self.faces,
        }


@dataclass(frozen=True)
class _Samples:
    points: np.ndarray  # (m, 3) mm
    weight: np.ndarray  # (m,) mm^2
    gradient2: np.ndarray  # (m,) |grad H|^2, 1/mm^4


def _bounds(surface: Surface) -> tuple[float, float, float, float]:
    if isinstance(surface, TSpline):
        return (*surface.mesh.s_range, *surface.mesh.t_range)
    u0, u1, v0, v1 = surface.bounds
    return float(u0), float(u1), float(v0), float(v1)


def _grid_size(surface: Surface, step_mm: float) -> tuple[int, int]:
    """Grid nodes along u and v for about ``step_mm`` between neighbours (the longest iso-line, from a coarse
    sample), at most ``MAX_FACE_NODES`` in all."""
    u0, u1, v0, v1 = _bounds(surface)
    uu, vv = np.meshgrid(np.linspace(u0, u1, 17), np.linspace(v0, v1, 17), indexing="ij")
    p = surface.evaluate(uu.ravel(), vv.ravel()).points.reshape(17, 17, 3)
    along_u = np.linalg.norm(np.diff(p, axis=0), axis=2).sum(axis=0).max()
    along_v = np.linalg.norm(np.diff(p, axis=1), axis=2).sum(axis=1).max()
    nu, nv = int(np.ceil(along_u / step_mm)) + 1, int(np.ceil(along_v / step_mm)) + 1
    shrink = max(1.0, np.sqrt(nu * nv / MAX_FACE_NODES))
    return max(3, int(nu / shrink)), max(3, int(nv / shrink))


def _face_samples(surface: Surface, step_mm: float) -> _Samples:
    """|grad H|^2 and the area each node stands for on a parameter grid of one face (module doc)."""
    u0, u1, v0, v1 = _bounds(surface)
    nu, nv = _grid_size(surface, step_mm)
    u, v = np.linspace(u0, u1, nu), np.linspace(v0, v1, nv)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    s = surface.evaluate(uu.ravel(), vv.ravel(), order=2)
    su, sv, suu, suv, svv = s.derivatives
    e, f, g = (np.einsum("ij,ij->i", a, b) for a, b in ((su, su), (su, sv), (sv, sv)))
    det = e * g - f * f
    normal = np.cross(su, sv)
    norm = np.linalg.norm(normal, axis=1)
    ok = det > 1e-10 * np.median(det)
    normal = normal / np.where(ok, norm, 1.0)[:, None]
    ll, mm, nn = (np.einsum("ij,ij->i", d, normal) for d in (suu, suv, svv))
    h = np.where(ok, (e * nn - 2 * f * mm + g * ll) / (2 * np.where(ok, det, 1.0)), 0.0).reshape(nu, nv)
    grad_u, grad_v = np.gradient(h, u, v)
    hu, hv = grad_u.ravel(), grad_v.ravel()
    grad2 = np.where(ok, (g * hu**2 - 2 * f * hu * hv + e * hv**2) / np.where(ok, det, 1.0), 0.0)
    # a node whose differences reach a degenerate node carries no figure
    bad = ~ok.reshape(nu, nv)
    reach = bad.copy()
    reach[1:] |= bad[:-1]
    reach[:-1] |= bad[1:]
    reach[:, 1:] |= bad[:, :-1]
    reach[:, :-1] |= bad[:, 1:]
    weight = np.sqrt(np.maximum(det, 0.0)) * np.outer(_trapezoid(u), _trapezoid(v)).ravel()
    weight = np.where(reach.ravel(), 0.0, weight)
    return _Samples(s.points, weight, grad2)


def _trapezoid(x: np.ndarray) -> np.ndarray:
    """Trapezoid-rule weights of the nodes x (parameter units)."""
    w = np.gradient(x)
    w[0] /= 2
    w[-1] /= 2
    return w


def surface_fairness(surfaces: Sequence[Surface], *, step_mm: float = 0.5,
                     labels: Callable[[np.ndarray], np.ndarray] | None = None) -> Fairness:
    """The fairness figure (module doc) of a model's faces.

    surfaces : its faces' exact surfaces (mm): B-spline surfaces over their bounds, or T-splines over their
    whole domain (a tube's periodic seam row counts at both ends, with half weight each);
    step_mm : grid spacing on them (mm); labels : optional function (m, 3) points -> (m,) region names
    (``analysis.model.region_labels``) for the per-region figures.
    """
    if step_mm <= 0:
        raise ValueError(f"step_mm must be positive, got {step_mm}")
    if not surfaces:
        raise ValueError("surface_fairness: no surfaces")
    parts = [_face_samples(surface, step_mm) for surface in surfaces]
    points = np.vstack([p.points for p in parts])
    weight = np.concatenate([p.weight for p in parts])
    grad2 = np.concatenate([p.gradient2 for p in parts])
    area = float(weight.sum())
    if area <= 0:
        raise ValueError("surface_fairness: the surfaces have no area")
    regions: dict[str, float] = {}
    region_area: dict[str, float] = {}
    typical: dict[str, float] = {}
    if labels is not None:
        names = np.asarray(labels(points))
        for name in sorted(set(names.tolist())):
            sel = names == name
            w = float(weight[sel].sum())
            if w > 0:
                regions[str(name)] = float(np.sqrt(np.sum(weight[sel] * grad2[sel]) / w))
                region_area[str(name)] = w
                typical[str(name)] = _weighted_median(np.sqrt(grad2[sel]), weight[sel])
    return Fairness(float(np.sqrt(np.sum(weight * grad2) / area)), regions, area, region_area, step_mm,
                    len(surfaces), _weighted_median(np.sqrt(grad2), weight), typical)


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    order = np.argsort(values)
    cum = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cum, 0.5 * cum[-1])])


def shape_fairness(shape, *, step_mm: float = 0.5,
                   labels: Callable[[np.ndarray], np.ndarray] | None = None) -> Fairness:
    """``surface_fairness`` of every face of an OpenCascade shape (its exact B-spline surfaces, read back)."""
    from bonecad.occ.brep import faces
    from bonecad.occ.read_faces import face_spline_surface

    surfaces = []
    for face in faces(shape):
        surface, _ = face_spline_surface(face)
        if surface is None:
            raise ValueError("shape_fairness: a face has no B-spline form")
        surfaces.append(surface)
    return surface_fairness(surfaces, step_mm=step_mm, labels=labels)
