"""The solver check: linear elasticity of the standard load cases (scikit-fem, pyamg), against beam theory.

The distal end's nodes are fixed; the proximal end's are moved as one rigid plate: along the axis
(axial), turned about the axis (torsion) or moved across it (bending, the plate free to tilt). The
stiffness is the reaction (force or torque) over the imposed motion. Elements are straight-sided
tetrahedra with linear (order 1) or quadratic (order 2) fields; a second-order mesh's curved boundary
nodes are not used (its corner tetrahedra carry the quadratic field).

Beam theory on the same mesh's cross-sections (``tets.cross_section``) between the two ends:
axial 1 / integral dz / EA(z); torsion 1 / integral dz / GJ(z) with Saint-Venant's J = A^4 / (4 pi^2 I_p)
of a solid section (exact for circles and ellipses; ``hollow=True``: J = I_p, exact for a circular tube);
bending, a cantilever of length L with the load at its tip: deflection integral (L - z)^2 / EI(z) dz plus
the shear term integral dz / (k G A), k = 0.5 for a thin tube, 0.9 for a solid section (Timoshenko).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import scipy.sparse as sp

from bonecad.fe.tets import cross_section, heights

Case = Literal["axial", "torsion", "bending"]


@dataclass(frozen=True)
class Stiffness:
    """One load case: the solver's stiffness (N/mm, or N mm/rad for torsion), beam theory's, the degrees of
    freedom and the solve's iterations."""

    case: str
    solver: float
    beam: float
    dofs: int
    iterations: int

    @property
    def ratio(self) -> float:
        return self.solver / self.beam


def _frame(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


def solve_cases(nodes: np.ndarray, tets: np.ndarray, modulus: np.ndarray, poisson: float, origin: np.ndarray,
                axis: np.ndarray, depth_mm: float, cases: tuple[Case, ...] = ("axial", "torsion"), order: int = 1,
                tol: float = 1e-10, hollow: bool = False) -> dict[str, Stiffness]:
    """The stiffness of each load case on straight tetrahedra (m, 4+) with element moduli (m,) MPa: the nodes
    within ``depth_mm`` of the lowest along ``axis`` fixed, those within ``depth_mm`` of the highest moved;
    ``hollow``: beam theory's torsion constant and shear factor of a tube."""
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    K, scalar = stiffness_matrix(nodes, tets, modulus, poisson, order)
    locs = np.repeat(scalar.doflocs.T, 3, axis=0)  # (ndof, 3), the position of each dof (interleaved x, y, z)
    comp = np.tile(np.arange(3), scalar.N)
    n_dofs = 3 * int(scalar.N)
    h = heights(locs, origin, axis)
    corners = nodes[np.unique(tets[:, :4])]
    hn = heights(corners, origin, axis)
    low, high = hn.min() + depth_mm, hn.max() - depth_mm
    fixed = np.flatnonzero(h <= low)
    top = h >= high
    centre = corners[hn >= high].mean(axis=0)
    e1, _ = _frame(axis)
    out: dict[str, Stiffness] = {}
    for case in cases:
        u = np.zeros(n_dofs)
        direction = axis if case == "axial" else e1
        if case == "torsion":
            moved = np.flatnonzero(top)
            r = locs[moved] - centre
            r -= np.outer(r @ axis, axis)
            u[moved] = np.cross(axis, r)[np.arange(len(moved)), comp[moved]]  # unit rotation (small angle)
        elif np.isclose(np.abs(direction).max(), 1.0):  # along a coordinate axis: the other components free
            moved = np.flatnonzero(top & np.isclose(np.abs(direction[comp]), 1.0))
            u[moved] = direction[comp[moved]]
        else:  # the plate moved as a whole
            moved = np.flatnonzero(top)
            u[moved] = direction[comp[moved]]
        prescribed = np.union1d(fixed, moved)
        free = np.setdiff1d(np.arange(n_dofs), prescribed)
        rhs = -K[free][:, prescribed] @ u[prescribed]
        x, iterations = _solve(K[free][:, free].tocsr(), rhs, locs[free], comp[free], tol, case)
        u[free] = x
        reaction = K[moved] @ u
        if case == "torsion":
            lever = np.cross(locs[moved] - centre, np.eye(3)[comp[moved]]) @ axis  # torque of a unit force
            value = float(reaction @ lever)
        else:
            value = float(reaction @ u[moved])
        beam = beam_estimate(nodes, tets, modulus, poisson, origin, axis, (low, high), case, hollow=hollow)
        out[case] = Stiffness(case, value, beam, n_dofs, iterations)
    return out


#: free degrees of freedom up to which the solve is direct (SuperLU: 2 s at 24 k P2 dofs where AMG-CG took
#: 12 s, measured); above, conjugate gradients preconditioned by smoothed-aggregation AMG (pyamg)
DIRECT_DOFS = 60000


def _solve(K: sp.csr_matrix, rhs: np.ndarray, locs: np.ndarray, comp: np.ndarray, tol: float,
           case: str) -> tuple[np.ndarray, int]:
    """K x = rhs: direct when small, else AMG-preconditioned CG; (x, iterations: 0 when direct)."""
    import pyamg
    import scipy.sparse.linalg as spla

    if K.shape[0] <= DIRECT_DOFS:
        return spla.spsolve(K.tocsc(), rhs), 0
    ml = pyamg.smoothed_aggregation_solver(K, B=_rigid_modes(locs, comp), max_coarse=500)
    count = [0]

    def step(_):
        count[0] += 1

    x, info = spla.cg(K, rhs, M=ml.aspreconditioner(), rtol=tol, maxiter=2000, callback=step)
    if info != 0:
        raise ArithmeticError(f"the {case} solve did not converge in {count[0]} iterations")
    return x, count[0]


def stiffness_matrix(nodes: np.ndarray, tets: np.ndarray, modulus: np.ndarray, poisson: float, order: int,
                     chunk: int = 4000) -> tuple[sp.csr_matrix, Any]:
    """The linear-elastic stiffness matrix (dofs interleaved: 3 i + component, i a scalar dof of the
    scikit-fem P1/P2 basis on the straight tetrahedra) with element moduli (m,) MPa, and that scalar basis.
    Assembled here from scikit-fem's basis gradients and quadrature, vectorised over elements (scikit-fem's
    own vector assembly loops over the 900 dof pairs of a P2 element: 7x slower, the same matrix)."""
    from skfem import Basis, ElementTetP1, ElementTetP2, MeshTet

    mesh = MeshTet(np.ascontiguousarray(nodes.T, dtype=np.float64), np.ascontiguousarray(tets[:, :4].T))
    basis = Basis(mesh, ElementTetP2() if order == 2 else ElementTetP1())
    modulus = np.asarray(modulus, dtype=np.float64)
    lam = modulus * poisson / ((1 + poisson) * (1 - 2 * poisson))
    mu = modulus / (2 * (1 + poisson))
    grads = np.stack([basis.basis[i][0].grad for i in range(basis.Nbfun)])  # (i, a, element, point)
    dx = basis.dx
    dofs = basis.element_dofs  # (i, element)
    rows, cols, vals = [], [], []
    eye = np.eye(3)
    for lo in range(0, dx.shape[0], chunk):
        sl = slice(lo, lo + chunk)
        gg = np.einsum("iaeq,jbeq,eq->eijab", grads[:, :, sl], grads[:, :, sl], dx[sl])  # d_a phi_i d_b phi_j
        lap = np.einsum("eijaa->eij", gg)
        k = (lam[sl, None, None, None, None] * gg.transpose(0, 1, 3, 2, 4)
             + mu[sl, None, None, None, None] * gg.transpose(0, 1, 4, 2, 3)
             + (mu[sl, None, None] * lap)[:, :, None, :, None] * eye[None, None, :, None, :])  # [e, i, a, j, b]
        gd = (3 * dofs[:, sl].T[:, :, None] + np.arange(3)).reshape(len(k), -1)
        rows.append(np.repeat(gd, gd.shape[1], axis=1).ravel())
        cols.append(np.tile(gd, (1, gd.shape[1])).ravel())
        vals.append(k.reshape(-1))
    n = 3 * basis.N
    K = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
    return K, basis


def _rigid_modes(locs: np.ndarray, comp: np.ndarray) -> np.ndarray:
    """(n, 6) rigid-body modes at dofs (positions, components): the near-null space for smoothed aggregation."""
    b = np.zeros((len(locs), 6))
    x = locs - locs.mean(axis=0)
    for c in range(3):
        b[comp == c, c] = 1.0
    # rotations about x, y, z: u = w x r
    for k, w in enumerate(np.eye(3)):
        rot = np.cross(w, x)
        b[:, 3 + k] = rot[np.arange(len(locs)), comp]
    return b


def beam_estimate(nodes: np.ndarray, tets: np.ndarray, modulus: np.ndarray, poisson: float, origin: np.ndarray,
                  axis: np.ndarray, span: tuple[float, float], case: Case, *, sections: int = 60,
                  hollow: bool = False) -> float:
    """Beam theory's stiffness between heights ``span`` (mm along ``axis`` from ``origin``) from
    ``sections`` cross-sections of the mesh (midpoint rule)."""
    lo, hi = span
    z = lo + (np.arange(sections) + 0.5) * (hi - lo) / sections
    dz = (hi - lo) / sections
    secs = [cross_section(nodes, tets[:, :4], modulus, origin, axis, float(h)) for h in z]
    shear = 1.0 / (2.0 * (1.0 + poisson))  # G / E
    if case == "axial":
        return 1.0 / sum(dz / s.ea_n for s in secs)
    if case == "torsion":
        def gj(s):
            e_mean = s.ea_n / s.area_mm2
            j = s.i_polar if hollow else s.area_mm2 ** 4 / (4 * np.pi ** 2 * s.i_polar)
            return shear * e_mean * j
        return 1.0 / sum(dz / gj(s) for s in secs)
    k = 0.5 if hollow else 0.9
    length = hi - lo
    bend = sum(dz * (hi - h) ** 2 / s.ei_xx for h, s in zip(z, secs))
    shear_term = sum(dz / (k * shear * s.ea_n) for s in secs)
    return 1.0 / (bend + shear_term) if length > 0 else float("nan")
