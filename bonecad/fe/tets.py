"""A tetrahedral mesh as arrays: node orders per file format, regions, end sets, cross-sections.

Node order of the 10-node tetrahedron (0-based; corners 0-3, then edge nodes):
gmsh (``.msh``)  4:(0,1) 5:(1,2) 6:(2,0) 7:(3,0) 8:(3,2) 9:(3,1);
VTK, Abaqus C3D10 and FEBio tet10: 4:(0,1) 5:(1,2) 6:(2,0) 7:(0,3) 8:(1,3) 9:(2,3).
The last two differ: ``GMSH_TO_VTK`` swaps them (the tests check it against
gmsh's own reference element and against the nodes' positions).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: gmsh's 10-node tetrahedron -> VTK / Abaqus C3D10 / FEBio tet10 (index into the gmsh row)
GMSH_TO_VTK = np.array([0, 1, 2, 3, 4, 5, 6, 7, 9, 8])
#: the edge (pair of corners) of each node 4-9 in the VTK/Abaqus/FEBio order
VTK_EDGES = np.array([[0, 1], [1, 2], [2, 0], [0, 3], [1, 3], [2, 3]])
REGIONS = ("distal", "shaft", "proximal")


@dataclass(frozen=True)
class TetMesh:
    """Tetrahedra of one solid, mm.

    nodes : (n, 3) float; tets : (m, 4) or (m, 10) int, gmsh's node order;
    sicn, gamma : (m,) gmsh's quality measures (signed inverse condition number, inscribed/circumscribed
    radius ratio; 1 for the regular tetrahedron); msh : the gmsh ``.msh`` file's bytes (format 4.1).
    """

    nodes: np.ndarray
    tets: np.ndarray
    sicn: np.ndarray
    gamma: np.ndarray
    msh: bytes = b""

    @property
    def order(self) -> int:
        return 2 if self.tets.shape[1] == 10 else 1

    def vtk_order(self) -> np.ndarray:
        """(m, 4|10) the elements in VTK / Abaqus / FEBio node order."""
        return self.tets if self.order == 1 else self.tets[:, GMSH_TO_VTK]

    def volumes(self) -> np.ndarray:
        """(m,) volume of each element's straight-sided corner tetrahedron, mm^3 (positive)."""
        return tet_volumes(self.nodes, self.tets[:, :4])

    def centroids(self) -> np.ndarray:
        return self.nodes[self.tets[:, :4]].mean(axis=1)


def tet_volumes(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(m,) signed volumes of tetrahedra (m, 4), mm^3."""
    p = nodes[tets]
    return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0


def quality_summary(values: np.ndarray) -> dict[str, float]:
    """Minimum, 1st percentile and median of a quality measure."""
    return {"min": round(float(np.min(values)), 4), "p1": round(float(np.percentile(values, 1)), 4),
            "median": round(float(np.median(values)), 4)}


def heights(points: np.ndarray, origin: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """(n,) mm along the unit ``axis`` from ``origin``."""
    return (np.asarray(points) - origin) @ axis


def element_regions(mesh: TetMesh, origin: np.ndarray, axis: np.ndarray,
                    bounds_mm: tuple[float, float]) -> dict[str, np.ndarray]:
    """Element indices per region: distal below ``bounds_mm[0]``, proximal above ``bounds_mm[1]``, the shaft
    between (element centroids' heights along the long axis, mm above ``origin``)."""
    h = heights(mesh.centroids(), origin, axis)
    lo, hi = bounds_mm
    return {"distal": np.flatnonzero(h < lo), "shaft": np.flatnonzero((h >= lo) & (h <= hi)),
            "proximal": np.flatnonzero(h > hi)}


def end_node_sets(mesh: TetMesh, origin: np.ndarray, axis: np.ndarray, depth_mm: float) -> dict[str, np.ndarray]:
    """Node indices within ``depth_mm`` of the lowest (distal) and highest (proximal) node along the axis."""
    h = heights(mesh.nodes, origin, axis)
    return {"distal_end": np.flatnonzero(h <= h.min() + depth_mm),
            "proximal_end": np.flatnonzero(h >= h.max() - depth_mm)}


@dataclass(frozen=True)
class Section:
    """One cross-section of the mesh perpendicular to the axis: height (mm), area (mm^2), its
    modulus-weighted area (N), the second moments about the section's centroid in the plane's two
    directions and the polar moment (mm^4), and the modulus-weighted ones (N mm^2)."""

    height_mm: float
    area_mm2: float
    ea_n: float
    i_xx: float
    i_yy: float
    i_polar: float
    ei_xx: float
    ei_yy: float
    ej_polar: float


def cross_section(nodes: np.ndarray, tets: np.ndarray, modulus: np.ndarray, origin: np.ndarray,
                  axis: np.ndarray, height_mm: float) -> Section:
    """The section of the straight tetrahedra (m, 4) by the plane at ``height_mm`` along ``axis``:
    exact polygons (a triangle or a quadrilateral per cut tetrahedron), their area and second moments,
    plain and weighted by each element's modulus (MPa)."""
    axis = np.asarray(axis, dtype=np.float64)
    e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    d = heights(nodes, origin, axis) - height_mm
    dt = d[tets]
    above = dt > 0
    count = above.sum(axis=1)
    polys: list[tuple[np.ndarray, np.ndarray]] = []  # (k, p, 2) polygon points in the plane, element index
    plane = np.stack([(nodes - origin) @ e1, (nodes - origin) @ e2], axis=1)

    def cut(a: np.ndarray, b: np.ndarray, rows: np.ndarray) -> np.ndarray:
        ia, ib = tets[rows, a], tets[rows, b]
        da, db = d[ia], d[ib]
        f = (da / (da - db))[:, None]
        return plane[ia] + f * (plane[ib] - plane[ia])

    for n_above in (1, 3):  # one corner apart: a triangle
        rows = np.flatnonzero(count == n_above)
        if not len(rows):
            continue
        lone = np.argmax(above[rows] if n_above == 1 else ~above[rows], axis=1)
        others = (lone[:, None] + np.arange(1, 4)[None, :]) % 4
        pts = np.stack([cut(lone, others[:, k], rows) for k in range(3)], axis=1)
        polys.append((pts, rows))
    rows = np.flatnonzero(count == 2)
    if len(rows):
        order = np.argsort(~above[rows], axis=1, kind="stable")  # the two above first
        a, b, c, dd = order.T
        pts = np.stack([cut(a, c, rows), cut(a, dd, rows), cut(b, dd, rows), cut(b, c, rows)], axis=1)
        polys.append((pts[:, [0, 1, 2]], rows))
        polys.append((pts[:, [0, 2, 3]], rows))
    tri = np.concatenate([p for p, _ in polys]) if polys else np.zeros((0, 3, 2))
    elem = np.concatenate([r for _, r in polys]) if polys else np.zeros(0, dtype=np.int64)
    e = modulus[elem]
    u, v = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    area = 0.5 * np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])
    s = tri.sum(axis=1)
    # integral of x x^T over a triangle: A / 12 (sum_i x_i x_i^T + s s^T)
    second = area[:, None, None] / 12.0 * (np.einsum("kpi,kpj->kij", tri, tri) + np.einsum("ki,kj->kij", s, s))
    first = area[:, None] * s / 3.0
    out = []
    for w in (np.ones_like(e), e):
        a_w = float(np.sum(w * area))
        c = np.sum(w[:, None] * first, axis=0) / max(a_w, 1e-300)
        m = np.sum(w[:, None, None] * second, axis=0) - a_w * np.outer(c, c)
        out.append((a_w, m[0, 0], m[1, 1]))
    (a0, ixx, iyy), (ea, eixx, eiyy) = out
    return Section(float(height_mm), a0, ea, float(ixx), float(iyy), float(ixx + iyy), float(eixx), float(eiyy),
                   float(eixx + eiyy))
