"""The Rhino T-Splines ``.iga`` text format (Bezier extraction for isogeometric analysis).

The format (Scott, Borden, Verhoosel, Sederberg, Hughes 2011, IJNME 88:126-156, and the T-Splines
plug-in's export): ``type surface``; ``nodeN`` and ``elemN``; one ``node x y z w`` line per global basis
function (control point, not homogeneous); per Bezier element ``belem k 3 3``, the k global indices
(0-based) of the functions non-zero on it, then k rows of 16 Bernstein coefficients (its extraction
rows; Bernstein index 4 j + i for B_i(s) B_j(t): s runs fastest); then sets: ``set n side NAME e SIDE ...``
(SIDE one of LEFT, RIGHT, BOTTOM, TOP: s = 0, s = 1, t = 0, t = 1 of element e), ``set n node NAME i ...``
and ``set n elem NAME e ...``.

Several T-spline patches go into one file through a condensation: each patch's local functions are
combinations of the global ones, ``local = G @ global`` (G: (n_local, n_global), sparse), and the row of a
global function g on an element is sum_a G[a, g] (local row of a). ``closed_surface`` builds G for a
periodic tube closed by two caps with a collapsed pole row:

- the tube's anchors are global functions as they are (C2 on the tube);
- each cap's pole row (all its control points one point: a degenerate row) becomes ONE global function,
  the sum of the row's functions. The row's functions one by one depend on the angle at the pole, where
  the parameterisation collapses, so none of them is in H^1 (the gradient grows as 1/r): kept apart they
  would spoil an analysis basis; their sum is a function of the distance from the pole only;
- each cap's ring row is written in the tube's end-row functions (the same curve: the cap was built on the
  tube's ring knots, then refined), so the basis is C0 across the ring and the surface is watertight;
- the cap's two inner rows are global functions of their own.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from bonecad.splines.tspline.tspline import TSpline

SIDES = ("LEFT", "RIGHT", "BOTTOM", "TOP")


@dataclass(frozen=True)
class IgaSurface:
    """Patches written as one analysis basis.

    patches : the T-splines; maps : per patch the (n_local, n_global) sparse G with local = G @ global;
    nodes : (n_global, 3) control points; weights : (n_global,); sets : (name, kind, entries) with kind
    "side" (entries: (element, SIDE) pairs), "node" or "elem" (entries: indices); element numbers run over
    the patches' Bezier elements in order.
    """

    patches: tuple[TSpline, ...]
    maps: tuple[sp.csr_matrix, ...]
    nodes: np.ndarray
    weights: np.ndarray
    sets: tuple[tuple[str, str, tuple], ...] = ()

    def element_offsets(self) -> np.ndarray:
        """(n_patches + 1,) the first element number of each patch."""
        return np.concatenate([[0], np.cumsum([p.extraction.n_elements for p in self.patches])])

    def check(self, tol: float = 1e-9) -> float:
        """Largest difference (mm) between each patch's homogeneous control points and the condensed
        global ones; ValueError above ``tol`` times the model's size."""
        size = float(np.ptp(self.nodes, axis=0).max()) or 1.0
        glob = np.hstack([self.nodes * self.weights[:, None], self.weights[:, None]])
        worst = 0.0
        for patch, g in zip(self.patches, self.maps):
            local = np.hstack([patch.control_points * patch.weights[:, None], patch.weights[:, None]])
            worst = max(worst, float(np.max(np.abs(g @ glob - local))))
        if worst > tol * size:
            raise ValueError(f"the patches' control points differ from the condensed basis by {worst:.3g} mm")
        return worst


def iga_text(surface: IgaSurface, comment: str = "", drop: float = 1e-14) -> str:
    """The ``.iga`` file of ``surface`` (see the module docstring); coefficients below ``drop`` are zero."""
    out = [f"# {line}" for line in comment.splitlines()]
    out += ["type surface", f"nodeN {len(surface.nodes)}",
            f"elemN {int(surface.element_offsets()[-1])}"]
    out += [f"node {x:.17g} {y:.17g} {z:.17g} {w:.17g}" for (x, y, z), w in zip(surface.nodes, surface.weights)]
    for patch, g in zip(surface.patches, surface.maps):
        ext = patch.extraction
        gc = g.tocsr()
        for e in range(ext.n_elements):
            anchors, coef = ext.element_operator(e)
            rows_local = coef.reshape(-1, 4, 4).transpose(0, 2, 1).reshape(-1, 16)  # 4 a + b -> 4 b + a
            ptr = gc.indptr
            plain = np.all(ptr[anchors + 1] - ptr[anchors] == 1)
            cols = gc.indices[np.minimum(ptr[anchors], max(gc.nnz - 1, 0))]  # the first global of each local one
            if plain and np.all(gc.data[ptr[anchors]] == 1.0) and len(np.unique(cols)) == len(cols):
                order = np.argsort(cols)  # each local function is one global one
                glob, rows = cols[order], rows_local[order]
            else:
                sub = gc[anchors]  # (k_local, n_global)
                glob = np.unique(sub.indices)
                rows = np.asarray(sub[:, glob].T @ rows_local)  # (k_global, 16)
            rows[np.abs(rows) < drop] = 0.0
            keep = np.any(rows != 0.0, axis=1)
            glob, rows = glob[keep], rows[keep]
            out.append(f"belem {len(glob)} 3 3")
            out.append(" ".join(map(str, glob)))
            out += [" ".join(map(repr, row)) for row in rows.tolist()]
    for name, kind, entries in surface.sets:
        flat = " ".join(f"{e} {side}" for e, side in entries) if kind == "side" else " ".join(map(str, entries))
        out.append(f"set {len(entries)} {kind} {name} {flat}")
    return "\n".join(out) + "\n"


def _row(patch: TSpline, which: int) -> np.ndarray:
    """Anchor indices of a tensor-product patch's first (0) or last (-1) t-row, ordered by s."""
    t_line = patch.mesh.anchors[:, 1]
    row = np.flatnonzero(t_line == (t_line.min() if which == 0 else t_line.max()))
    return row[np.argsort(patch.mesh.anchors[row, 0])]


def _trace_map(cap: TSpline, ring: np.ndarray, t_cap: float, tube: TSpline, tube_row: np.ndarray,
               t_tube: float, samples: int = 400) -> np.ndarray:
    """(len(ring), len(tube_row)) T with the tube's end-row functions' traces = the cap's ring functions'
    traces @ T (the cap's ring space holds the tube's); ValueError when it does not."""
    s0, s1 = tube.mesh.s_range
    s = s0 + (np.arange(samples) + 0.5) * (s1 - s0) / samples
    cap_trace = cap.basis_matrix(s, np.full(samples, t_cap)).toarray()
    tube_trace = tube.basis_matrix(s, np.full(samples, t_tube)).toarray()
    rest = np.setdiff1d(np.arange(tube.n_control), tube_row)
    if np.max(np.abs(tube_trace[:, rest])) > 1e-12 or np.max(np.abs(np.delete(cap_trace, ring, axis=1))) > 1e-12:
        raise ValueError("the end rows do not carry the boundary curves alone")
    t_map, *_ = np.linalg.lstsq(cap_trace[:, ring], tube_trace[:, tube_row], rcond=None)
    residual = float(np.max(np.abs(cap_trace[:, ring] @ t_map - tube_trace[:, tube_row])))
    if residual > 1e-10:
        raise ValueError(f"the cap's ring functions do not span the tube's end functions (residual {residual:.2g})")
    t_map[np.abs(t_map) < 1e-13] = 0.0
    return t_map


def closed_surface(tube: TSpline, caps: Sequence[tuple[str, TSpline]], tol: float = 1e-9) -> IgaSurface:
    """A periodic tube (clamped in t) and its caps (end "distal" at the tube's t start, "proximal" at its end;
    tensor-product patches periodic in s with one collapsed row) as one C0 basis; see the module docstring.
    Sets: side sets ``<end>_ring`` (the tube's end edges), element sets ``tube`` and ``<end>_cap``, node
    sets ``<end>_pole``."""
    if tube.mesh.s_period is None:
        raise ValueError("closed_surface: the tube must be periodic in s")
    if not (tube.polynomial and all(c.polynomial for _, c in caps)):
        raise ValueError("closed_surface: rational patches are not supported (all weights must be 1)")
    n_tube = tube.n_control
    nodes = [tube.control_points]
    rows_g, cols_g, vals_g = [np.arange(n_tube)], [np.arange(n_tube)], [np.ones(n_tube)]
    maps_coo = [(rows_g, cols_g, vals_g, n_tube)]
    offset = n_tube
    pole_nodes: dict[str, int] = {}
    t0, t1 = tube.mesh.t_range
    cap_maps = []
    for end, cap in caps:
        first, last = _row(cap, 0), _row(cap, -1)
        size = float(np.ptp(cap.control_points, axis=0).max())
        collapsed = [np.ptp(cap.control_points[r], axis=0).max() <= tol * size for r in (first, last)]
        if collapsed.count(True) != 1:
            raise ValueError(f"the {end} cap must have exactly one collapsed row, has {collapsed.count(True)}")
        pole, ring = (first, last) if collapsed[0] else (last, first)
        t_cap = cap.mesh.t_range[1] if collapsed[0] else cap.mesh.t_range[0]
        t_tube = t0 if end == "distal" else t1
        tube_row = _row(tube, 0 if end == "distal" else -1)
        t_map = _trace_map(cap, ring, t_cap, tube, tube_row, t_tube)
        inner = np.setdiff1d(np.arange(cap.n_control), np.concatenate([pole, ring]))
        r_list, c_list, v_list = [], [], []
        # inner anchors: their own globals
        r_list.append(inner)
        c_list.append(offset + np.arange(len(inner)))
        v_list.append(np.ones(len(inner)))
        nodes.append(cap.control_points[inner])
        offset += len(inner)
        # the pole: one global
        pole_nodes[end] = offset
        r_list.append(pole)
        c_list.append(np.full(len(pole), offset))
        v_list.append(np.ones(len(pole)))
        nodes.append(cap.control_points[pole[:1]])
        offset += 1
        # the ring: the tube's end-row functions
        rr, cc = np.nonzero(t_map)
        r_list.append(ring[rr])
        c_list.append(tube_row[cc])
        v_list.append(t_map[rr, cc])
        cap_maps.append((r_list, c_list, v_list, cap.n_control))
    n_global = offset
    maps = []
    for r_list, c_list, v_list, n_local in maps_coo + cap_maps:
        maps.append(sp.csr_matrix((np.concatenate(v_list), (np.concatenate(r_list), np.concatenate(c_list))),
                                  shape=(n_local, n_global)))
    all_nodes = np.vstack(nodes)
    patches = (tube, *(c for _, c in caps))
    ext = tube.extraction
    sets: list[tuple[str, str, tuple]] = []
    for end, _ in caps:
        t_end, col, side = (t0, 0, "BOTTOM") if end == "distal" else (t1, 1, "TOP")
        ring_elems = np.flatnonzero(np.isclose(ext.t_bounds[:, col], t_end))
        sets.append((f"{end}_ring", "side", tuple((int(e), side) for e in ring_elems)))
    offsets = np.concatenate([[0], np.cumsum([p.extraction.n_elements for p in patches])])
    sets.append(("tube", "elem", tuple(range(int(offsets[1])))))
    for k, (end, _) in enumerate(caps):
        sets.append((f"{end}_cap", "elem", tuple(range(int(offsets[k + 1]), int(offsets[k + 2])))))
        sets.append((f"{end}_pole", "node", (pole_nodes[end],)))
    surface = IgaSurface(patches, tuple(maps), all_nodes, np.ones(n_global), tuple(sets))
    surface.check(tol)
    return surface
