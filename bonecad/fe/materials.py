"""Bone stiffness from a CT: Hounsfield units -> density -> Young's modulus, integrated over each element.

HU -> equivalent mineral density rho_QCT (g/cm^3) by the scanner's calibration (``[fe] hu_to_density``:
slope, intercept, from a density phantom scanned with the bone); rho_QCT -> ash density by Schileo et al.
2008 (J Biomech 41:356-367): rho_ash = 0.877 rho_QCT + 0.079; ash -> apparent density: rho_ash / rho_app = 0.6
(Keller 1994; Schileo 2008); density -> E (MPa) by a power law E = a rho^b (``[fe] modulus_law``, of the
ash or apparent density, ``[fe] modulus_density``): the default is Keller 1994 (J Biomech 27:1159-1168),
E = 10500 rho_ash^2.57 MPa, fitted over cortical and trabecular bone of the femur and spine (rho_ash
0.03-1.22); the site-specific trabecular laws of Morgan, Bayraktar, Keaveny 2003 (J Biomech 36:897-904,
apparent density) are E = 15520 rho^1.93 (proximal tibia), 6850 rho^1.49 (femoral neck), 15010 rho^2.18
(greater trochanter), 8920 rho^1.83 (pooled).

Each element's modulus is E(x) averaged over the element, E taken at points of the trilinear
interpolation of the CT (not at the element's centre): a 4-point rule on each of the 8^k sub-tetrahedra
of k uniform subdivisions, k chosen so that the median sub-tetrahedron edge is at most ``[fe]
quadrature_voxels`` voxels. The moduli are then grouped into at most ``[fe] materials`` materials
(bins of equal width in log E; each bin's modulus is the volume-weighted mean of its elements').
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import map_coordinates

# 4-point rule for tetrahedra, degree 2 (barycentric a, b, b, b), equal weights
_A, _B = 0.5854101966249685, 0.1381966011250105
_RULE = np.array([[_A, _B, _B, _B], [_B, _A, _B, _B], [_B, _B, _A, _B], [_B, _B, _B, _A]])
# one uniform subdivision of a tetrahedron into 8 (barycentric corners of each child; edge midpoints)
_MID = {(i, j): np.eye(4)[[i, j]].mean(axis=0) for i in range(4) for j in range(i + 1, 4)}


def _children() -> np.ndarray:
    v = np.eye(4)
    m = _MID
    kids = [[v[0], m[0, 1], m[0, 2], m[0, 3]], [m[0, 1], v[1], m[1, 2], m[1, 3]],
            [m[0, 2], m[1, 2], v[2], m[2, 3]], [m[0, 3], m[1, 3], m[2, 3], v[3]],
            # the inner octahedron, cut along its diagonal (0,1)-(2,3) into four
            [m[0, 1], m[2, 3], m[0, 2], m[0, 3]], [m[0, 1], m[2, 3], m[0, 3], m[1, 3]],
            [m[0, 1], m[2, 3], m[1, 3], m[1, 2]], [m[0, 1], m[2, 3], m[1, 2], m[0, 2]]]
    return np.array(kids)  # (8, 4 corners, 4 barycentric)


_KIDS = _children()


def quadrature(levels: int) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric points (q, 4) and weights (q,) summing to 1: the 4-point rule on the 8^levels
    sub-tetrahedra of ``levels`` uniform subdivisions (all of equal volume)."""
    corners = np.eye(4)[None]  # (1, 4, 4)
    for _ in range(levels):
        corners = np.einsum("kcb,nbd->nkcd", _KIDS, corners).reshape(-1, 4, 4)
    pts = np.einsum("qc,ncd->nqd", _RULE, corners).reshape(-1, 4)
    return pts, np.full(len(pts), 1.0 / len(pts))


@dataclass(frozen=True)
class Calibration:
    """HU -> rho_QCT = slope HU + intercept (g/cm^3), then ash and apparent densities, then E = a rho^b (MPa)
    of the ash or apparent density, floored at ``min_modulus_mpa``."""

    slope: float
    intercept: float
    ash_from_qct: tuple[float, float]
    ash_share_of_apparent: float
    law: tuple[float, float]
    law_density: str
    min_modulus_mpa: float

    def modulus(self, hu: np.ndarray) -> np.ndarray:
        """E (MPa) at Hounsfield units ``hu``."""
        qct = self.slope * np.asarray(hu, dtype=np.float64) + self.intercept
        ash = np.maximum(self.ash_from_qct[0] * qct + self.ash_from_qct[1], 0.0)
        rho = ash if self.law_density == "ash" else ash / self.ash_share_of_apparent
        return np.maximum(self.law[0] * rho ** self.law[1], self.min_modulus_mpa)


def sample_trilinear(hu: np.ndarray, world_to_index, points: np.ndarray, outside: float) -> np.ndarray:
    """HU of the trilinear interpolation of the volume ``hu`` [k, j, i] at world points (n, 3);
    ``world_to_index`` maps (n, 3) world mm to fractional (i, j, k); ``outside`` beyond the volume."""
    ijk = world_to_index(points)
    return map_coordinates(hu, ijk[:, ::-1].T, order=1, mode="constant", cval=outside)


def subdivision_levels(nodes: np.ndarray, tets: np.ndarray, voxel_mm: float, voxels: float) -> int:
    """Uniform subdivisions that bring the median element edge to ``voxels`` voxels or below (at most 3)."""
    p = nodes[tets[:, :4]]
    edge = float(np.median(np.linalg.norm(p[:, 1] - p[:, 0], axis=1)))
    return int(min(3, max(0, np.ceil(np.log2(max(edge / (voxels * voxel_mm), 1.0))))))


def element_moduli(nodes: np.ndarray, tets: np.ndarray, modulus_at, levels: int, chunk: int = 1024) -> np.ndarray:
    """(m,) E averaged over each straight tetrahedron (m, 4+): ``modulus_at`` (n, 3) world mm -> (n,) MPa
    at the points of ``quadrature(levels)``."""
    bary, w = quadrature(levels)
    out = np.empty(len(tets))
    for lo in range(0, len(tets), chunk):
        p = nodes[tets[lo:lo + chunk, :4]]  # (c, 4, 3)
        pts = np.einsum("qc,ncd->nqd", bary, p).reshape(-1, 3)
        out[lo:lo + chunk] = modulus_at(pts).reshape(len(p), -1) @ w
    return out


@dataclass(frozen=True)
class Materials:
    """Element moduli grouped into materials: ``element_material`` (m,) index into ``moduli_mpa`` (k,);
    ``element_modulus_mpa`` (m,) before grouping; ``max_grouping_error`` the largest relative change an
    element's modulus took by the grouping; ``source``: "ct" or "homogeneous"."""

    element_material: np.ndarray
    moduli_mpa: np.ndarray
    element_modulus_mpa: np.ndarray
    poisson: float
    max_grouping_error: float
    source: str


def group_moduli(element_modulus: np.ndarray, volumes: np.ndarray, count: int, poisson: float,
                 source: str = "ct") -> Materials:
    """At most ``count`` materials: bins of equal width in log E, each the volume-weighted mean of its
    elements' moduli (empty bins dropped)."""
    e = np.asarray(element_modulus, dtype=np.float64)
    lo, hi = np.log(e.min()), np.log(e.max())
    if hi - lo < 1e-12 or count == 1:
        bins = np.zeros(len(e), dtype=np.int64)
    else:
        bins = np.minimum(((np.log(e) - lo) / (hi - lo) * count).astype(np.int64), count - 1)
    used, index = np.unique(bins, return_inverse=True)
    weight = np.bincount(index, weights=volumes)
    moduli = np.bincount(index, weights=volumes * e) / weight
    err = float(np.max(np.abs(moduli[index] / e - 1.0)))
    return Materials(index, moduli, e, poisson, err, source)
