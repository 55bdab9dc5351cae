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
from typing import Literal

import numpy as np

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


def solve_case(nodes: np.ndarray, tets: np.ndarray, modulus: np.ndarray, poisson: float, origin: np.ndarray,
               axis: np.ndarray, depth_mm: float, case: Case, order: int = 1, tol: float = 1e-10) -> Stiffness:
    """The stiffness of one load case on straight tetrahedra (m, 4+) with element moduli (m,) MPa."""
    import pyamg
    import scipy.sparse.linalg as spla
    from skfem import Basis, BilinearForm, ElementTetP0, ElementTetP1, ElementTetP2, ElementVector, MeshTet, asm
    from skfem.helpers import ddot, sym_grad, trace, eye

    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    mesh = MeshTet(np.ascontiguousarray(nodes.T), np.ascontiguousarray(tets[:, :4].T))
    basis = Basis(mesh, ElementVector(ElementTetP2() if order == 2 else ElementTetP1()))
    e_field = basis.with_element(ElementTetP0()).interpolate(np.asarray(modulus, dtype=np.float64))

    @BilinearForm
    def stiffness(u, v, w):
        lam = w.e * poisson / ((1 + poisson) * (1 - 2 * poisson))
        mu = w.e / (2 * (1 + poisson))
        eps = sym_grad(u)
        return ddot(2.0 * mu * eps + lam * eye(trace(eps), 3), sym_grad(v))

    K = asm(stiffness, basis, e=e_field).tocsr()
    locs = basis.doflocs.T  # (ndof, 3), the position of each dof
    comp = np.empty(basis.N, dtype=np.int64)
    for c, idx in enumerate(basis.split_indices()):
        comp[idx] = c
    h = heights(locs, origin, axis)
    hn = heights(nodes[np.unique(tets[:, :4])], origin, axis)
    low, high = hn.min() + depth_mm, hn.max() - depth_mm
    fixed = np.flatnonzero(h <= low)
    top = h >= high
    e1, e2 = _frame(axis)
    centre = nodes[np.unique(tets[:, :4])][heights(nodes[np.unique(tets[:, :4])], origin, axis) >= high].mean(axis=0)
    u = np.zeros(basis.N)
    if case == "axial":
        moved = np.flatnonzero(top & np.isclose(np.abs(_axis_component(comp, axis)), 1.0))
        u[moved] = _axis_component(comp, axis)[moved]  # unit motion along the axis
        if not len(moved):  # an axis off the coordinate axes: prescribe the full displacement
            moved = np.flatnonzero(top)
            u[moved] = axis[comp[moved]]
    elif case == "torsion":
        moved = np.flatnonzero(top)
        r = locs[moved] - centre
        r -= np.outer(r @ axis, axis)
        u[moved] = np.cross(axis, r)[np.arange(len(moved)), comp[moved]]  # unit rotation, small angle
    else:
        moved = np.flatnonzero(top & np.isclose(np.abs(e1[comp]), 1.0))
        u[moved] = e1[comp[moved]]
        if not len(moved):
            moved = np.flatnonzero(top)
            u[moved] = np.outer(np.ones(len(moved)), e1)[np.arange(len(moved)), comp[moved]]
    prescribed = np.union1d(fixed, moved)
    free = np.setdiff1d(np.arange(basis.N), prescribed)
    rhs = -K[free][:, prescribed] @ u[prescribed]
    Kff = K[free][:, free].tocsr()
    ml = pyamg.smoothed_aggregation_solver(Kff, B=_rigid_modes(locs[free], comp[free]), max_coarse=500)
    iterations = [0]

    def count(_):
        iterations[0] += 1

    x, info = spla.cg(Kff, rhs, M=ml.aspreconditioner(), rtol=tol, maxiter=2000, callback=count)
    if info != 0:
        raise ArithmeticError(f"the {case} solve did not converge in {iterations[0]} iterations")
    u[free] = x
    reaction = K[moved] @ u
    if case == "torsion":
        r = locs[moved] - centre
        lever = np.cross(r, np.eye(3)[comp[moved]]) @ axis  # torque of a unit force along each dof
        value = float(reaction @ lever)
    elif case == "axial":
        value = float(reaction @ u[moved])
    else:
        value = float(reaction @ u[moved])
    return Stiffness(case, value, beam_estimate(nodes, tets, modulus, poisson, origin, axis, (low, high), case),
                     int(basis.N), iterations[0])


def _axis_component(comp: np.ndarray, axis: np.ndarray) -> np.ndarray:
    return axis[comp]


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
