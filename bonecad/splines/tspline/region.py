"""An open rectangular region of a T-spline as a T-spline of its own, clamped on all four sides.

The region [s_a, s_b] x [t_a, t_b] (on knot lines of the T-mesh) keeps the
T-mesh's edges inside it and gets clamped boundaries; its control points are
solved by least squares on points of every Bezier element, so that the new
T-spline reproduces the old surface on the region. That is exact when the
old surface restricted to the region lies in the new spline space: the
restricted T-mesh first, then with every T-junction extension added (the
Bezier mesh), then the full tensor-product grid of the region's lines, which
always holds it (every old blending function is a C2 piecewise bicubic on
that grid). The first that reproduces the surface to ``tol_mm`` is returned.
"""
from __future__ import annotations

import numpy as np

from bonecad.splines.tspline.extraction import bezier_mesh_edges
from bonecad.splines.tspline.tmesh import END_LINES, TMesh
from bonecad.splines.tspline.tspline import TSpline

#: points per element side for the least-squares reproduction
_SAMPLES = 5


def _line_range(values: np.ndarray, a: float, b: float, tol: float, name: str) -> tuple[int, int]:
    near_a = np.flatnonzero(np.abs(values - a) <= tol)
    near_b = np.flatnonzero(np.abs(values - b) <= tol)
    if not (near_a.size and near_b.size) or not a < b:
        raise ValueError(f"{name} range [{a}, {b}]: both ends must be knot lines of the T-mesh, in order")
    return int(near_a[-1]), int(near_b[0])


def _clamp(edges_along: np.ndarray, edges_across: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pad a sub-grid with the zero-width end strips of a clamped direction (rows: its lines)."""
    e = END_LINES - 1
    along = np.vstack([np.ones((e, edges_along.shape[1]), bool), edges_along, np.ones((e, edges_along.shape[1]), bool)])
    along[e], along[-e - 1] = True, True
    across = np.hstack([np.repeat(edges_across[:, :1], e, axis=1), edges_across,
                        np.repeat(edges_across[:, -1:], e, axis=1)])
    return along, across


def _sub_mesh(mesh: TMesh, s_edges: np.ndarray, t_edges: np.ndarray, i: np.ndarray, j: np.ndarray,
              s_vals: np.ndarray, t_vals: np.ndarray) -> TMesh:
    """The region's mesh: edges between lines i (s, consecutive, maybe wrapped) and j (t)."""
    s_n = mesh.shape[0]
    seg = i[:-1] % (s_n if mesh.periodic else s_n - 1)
    s_sub = s_edges[j][:, seg]  # (nt, ns - 1)
    t_sub = t_edges[i % s_n][:, j[:-1]]  # (ns, nt - 1)
    s_sub, t_sub = _clamp(s_sub, t_sub)  # the clamped t ends
    t_sub, s_sub = _clamp(t_sub, s_sub)  # the clamped s ends
    e = END_LINES - 1
    lines_s = np.concatenate([[s_vals[0]] * e, s_vals, [s_vals[-1]] * e])
    lines_t = np.concatenate([[t_vals[0]] * e, t_vals, [t_vals[-1]] * e])
    sub = TMesh(lines_s - lines_s[0], lines_t - lines_t[0], s_sub, t_sub)
    sub.validate()
    return sub


def open_region(ts: TSpline, s_range: tuple[float, float], t_range: tuple[float, float], *,
                tol_mm: float = 1e-10) -> tuple[TSpline, str]:
    """The T-spline's surface on [s_a, s_b] x [t_a, t_b] as an open, clamped T-spline whose
    parameters start at (0, 0): new(s - s_a, t - t_a) = old(s, t).

    s_range : knot values of two s-lines (s_b - s_a < period when s is periodic; s_b may exceed
    the period's end). t_range : of two t-lines. Returns (T-spline, which mesh held it:
    "restricted", "extended" or "grid"). ValueError when no candidate reproduces it.
    """
    mesh = ts.mesh
    scale = max(np.ptp(mesh.s_lines), np.ptp(mesh.t_lines), mesh.s_period or 0.0)
    tol = 1e-9 * scale
    s_a, s_b = s_range
    if mesh.s_period is not None:
        if not 0 < s_b - s_a < mesh.s_period:
            raise ValueError(f"s range [{s_a}, {s_b}]: expected 0 < s_b - s_a < the period {mesh.s_period}")
        s_n = mesh.shape[0]
        unwrapped = np.concatenate([mesh.s_value(np.arange(s_n)), mesh.s_value(np.arange(s_n, 2 * s_n))])
        lo = mesh.s_lines[0]
        shift = np.floor((s_a - lo) / mesh.s_period) * mesh.s_period
        ia, ib = _line_range(unwrapped + shift, s_a, s_b, tol, "s")
        i = np.arange(ia, ib + 1)
        s_vals = unwrapped[i] + shift
    else:
        ia, ib = _line_range(mesh.s_lines, s_a, s_b, tol, "s")
        ia, ib = max(ia, END_LINES - 1), min(ib, mesh.shape[0] - END_LINES)
        i = np.arange(ia, ib + 1)
        s_vals = mesh.s_lines[i]
    ja, jb = _line_range(mesh.t_lines, *t_range, tol, "t")
    ja, jb = max(ja, END_LINES - 1), min(jb, mesh.shape[1] - END_LINES)
    j = np.arange(ja, jb + 1)
    t_vals = mesh.t_lines[j]
    ext_s, ext_t = bezier_mesh_edges(mesh)
    candidates = (("restricted", mesh.s_edges, mesh.t_edges), ("extended", ext_s, ext_t),
                  ("grid", np.ones_like(mesh.s_edges), np.ones_like(mesh.t_edges)))
    worst = []
    for name, s_edges, t_edges in candidates:
        try:
            sub = _sub_mesh(mesh, s_edges, t_edges, i, j, s_vals, t_vals)
        except ValueError as exc:
            worst.append(f"{name}: {exc}")
            continue
        blank = TSpline(sub, np.zeros((len(sub.anchors), 3)), np.ones(len(sub.anchors)))
        ext = blank.extraction
        u = (np.arange(_SAMPLES) + 0.5) / _SAMPLES
        uu, vv = (g.ravel() for g in np.meshgrid(u, u, indexing="ij"))
        s = (ext.s_bounds[:, :1] + np.diff(ext.s_bounds, axis=1) * uu).ravel()
        t = (ext.t_bounds[:, :1] + np.diff(ext.t_bounds, axis=1) * vv).ravel()
        target = ts.evaluate(s + s_vals[0], t + t_vals[0]).points
        basis = blank.basis_matrix(s, t).toarray()
        cp = np.linalg.lstsq(basis, target, rcond=None)[0]
        new = blank.with_control_points(cp)
        err = float(np.abs(new.evaluate(s, t).points - target).max())
        if err <= tol_mm:
            return new, name
        worst.append(f"{name}: {err:.3g} mm")
    raise ValueError("no clamped T-mesh of the region reproduces the surface: " + "; ".join(worst))
