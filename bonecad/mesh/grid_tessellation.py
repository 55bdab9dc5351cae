"""Parameter-grid triangles of untrimmed spline faces, all faces in one batch, refined until
each covers its exact area.

Needs only a :class:`~bonecad.splines.surface.SurfaceSet` (faces by index) and
the tolerances of :class:`GridTolerances`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from bonecad.mesh.sampling import triangle_areas
from bonecad.splines.surface import SurfaceSet
from bonecad.splines.knots import breakpoints

#: samples per knot span and cross lines per face used to size a grid
_SIZE_SAMPLES, _SIZE_LINES = 5, 5

log = logging.getLogger(__name__)


class GridTolerances(Protocol):
    """deflection_mm : chord sag aimed at; angular_deflection_rad : turn per segment; max_edge_mm : segment
    length; allowed_shortfall(exact_area_mm2) : relative area shortfall accepted per face."""

    @property
    def deflection_mm(self) -> float: ...
    @property
    def angular_deflection_rad(self) -> float: ...
    @property
    def max_edge_mm(self) -> float: ...

    def allowed_shortfall(self, exact_area_mm2: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class GridTessellation:
    """Grid triangles of some faces (n nodes, m triangles), numbered from 0.

    uv : (n, 2) parameters; triangles : (m, 3) int, oriented out of the material;
    node_face, triangle_face : (n,), (m,) int, face index;
    area_mm2 : (F,) exact area of every gridded face (0 elsewhere);
    points, su, sv : (n, 3) S, S_u, S_v at the nodes (mm)
    """

    uv: np.ndarray
    triangles: np.ndarray
    node_face: np.ndarray
    triangle_face: np.ndarray
    area_mm2: np.ndarray
    points: np.ndarray
    su: np.ndarray
    sv: np.ndarray


def _grid_counts(
    sset: SurfaceSet, faces: list[int], breaks: list[tuple[np.ndarray, np.ndarray]], tolerances: GridTolerances,
    factor: np.ndarray,
) -> list[list[np.ndarray]]:
    """Segments per knot span, per face and direction, from sampled iso-lines.

    A span is split into n segments so that (a) no segment is longer than
    ``max_edge_mm``, (b) the sag of a chord, |C''| (span / n)^2 / 8 with C''
    from second differences, stays below ``deflection_mm``, and (c) the
    iso-line turns by at most ``angular_deflection_rad`` per segment.
    """
    m = _SIZE_SAMPLES
    t = np.linspace(0.0, 1.0, m)
    c = np.linspace(0.0, 1.0, _SIZE_LINES)
    factor = np.asarray(factor, dtype=np.float64)
    faces_arr = np.asarray(faces, dtype=np.int64)
    out: list[list] = [[None] * len(faces), [None] * len(faces)]
    # faces with as many knot spans each way are sized together
    by_spans: dict[tuple[int, int], list[int]] = {}
    for i, (bu, bv) in enumerate(breaks):
        by_spans.setdefault((len(bu), len(bv)), []).append(i)
    for members in by_spans.values():
        fids = faces_arr[members]
        all_u = np.array([breaks[i][0] for i in members])
        all_v = np.array([breaks[i][1] for i in members])
        for direction in (0, 1):
            along, across = (all_u, all_v) if direction == 0 else (all_v, all_u)
            lo, hi = along[:, :-1], along[:, 1:]  # (F, S)
            par = lo[..., None] + (hi - lo)[..., None] * t  # (F, S, m)
            # cross lines: evenly spaced, mid-span and at the knots (a repeated line changes no maximum)
            cross = np.concatenate(
                [across[:, :1] + (across[:, -1:] - across[:, :1]) * c, 0.5 * (across[:, :-1] + across[:, 1:]), across],
                axis=1,
            )  # (F, K)
            count, spans = lo.shape
            shape = (count, spans, cross.shape[1], m)
            grid_a = np.broadcast_to(par[:, :, None, :], shape)
            grid_c = np.broadcast_to(cross[:, None, :, None], shape)
            uu, vv = (grid_a, grid_c) if direction == 0 else (grid_c, grid_a)
            fid = np.broadcast_to(fids[:, None, None, None], shape)
            pts = sset.evaluate(fid.ravel(), uu.ravel(), vv.ravel()).points.reshape(*shape, 3)
            d = np.diff(pts, axis=3)
            size = np.linalg.norm(d, axis=4)
            dn = d / np.maximum(size[..., None], 1e-300)
            turn = np.arccos(np.clip(np.einsum("fskmj,fskmj->fskm", dn[..., 1:, :], dn[..., :-1, :]), -1, 1))
            length = size.sum(axis=3).max(axis=2)  # (F, S): longest sampled iso-line per span
            second = np.linalg.norm(pts[..., 2:, :] - 2 * pts[..., 1:-1, :] + pts[..., :-2, :], axis=4).max(axis=(2, 3))
            turns = (turn.sum(axis=3) * (m - 1) / max(m - 2, 1)).max(axis=2)
            n = np.maximum.reduce(
                [
                    np.ones_like(length),
                    np.ceil(length / tolerances.max_edge_mm),
                    np.ceil((m - 1) * np.sqrt(second / (8.0 * tolerances.deflection_mm))),
                    np.ceil(turns / tolerances.angular_deflection_rad),
                ]
            )
            n = np.minimum(n * factor[members][:, None], 1000).astype(np.int64)
            for row, i in enumerate(members):
                out[direction][i] = n[row]
    return out


def _subdivide(breaks: np.ndarray, counts: np.ndarray) -> np.ndarray:
    parts = [np.linspace(a, b, n, endpoint=False) for a, b, n in zip(breaks[:-1], breaks[1:], counts)]
    return np.concatenate(parts + [breaks[-1:]])


def _grid_pass(
    sset: SurfaceSet, faces: list[int], reversed_faces: np.ndarray, tolerances: GridTolerances, factor: np.ndarray
):
    """Parameter-grid triangles of untrimmed spline faces, all faces in one batch.

    Returns uv, triangles (local to this pass), node_face, triangle_face and the
    exact area per face (2x2 Gauss-Legendre per grid cell of |S_u x S_v|).
    """
    breaks = []
    for f in faces:
        s = sset.surfaces[f]
        if s is None:
            raise ValueError(f"face {f} has no spline surface to grid")
        u0, u1, v0, v1 = s.bounds
        breaks.append((breakpoints(s.knots_u, u0, u1), breakpoints(s.knots_v, v0, v1)))
    counts_u, counts_v = _grid_counts(sset, faces, breaks, tolerances, factor)
    grids = [(_subdivide(bu, cu), _subdivide(bv, cv)) for (bu, bv), cu, cv in zip(breaks, counts_u, counts_v)]
    # faces with the same grid size share one index pattern: build them together
    by_size: dict[tuple[int, int], list[int]] = {}
    for i, (gu, gv) in enumerate(grids):
        by_size.setdefault((len(gu), len(gv)), []).append(i)
    faces_arr = np.asarray(faces, dtype=np.int64)
    uvs: list[np.ndarray] = []
    tris: list[np.ndarray] = []
    node_faces: list[np.ndarray] = []
    tri_faces: list[np.ndarray] = []
    quad_list: list[np.ndarray] = []
    quad_faces: list[np.ndarray] = []
    offset = 0
    for (nu, nv), members in by_size.items():
        count = len(members)
        fids = faces_arr[members]
        gu = np.array([grids[i][0] for i in members])  # (F, nu)
        gv = np.array([grids[i][1] for i in members])  # (F, nv)
        uu = np.broadcast_to(gu[:, :, None], (count, nu, nv))
        vv = np.broadcast_to(gv[:, None, :], (count, nu, nv))
        uvs.append(np.column_stack([uu.ravel(), vv.ravel()]))
        idx = np.arange(nu * nv).reshape(nu, nv)
        a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
        pattern = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
        tri = pattern[None] + (offset + nu * nv * np.arange(count))[:, None, None]  # (F, T, 3)
        flip = reversed_faces[fids]
        tri[flip] = tri[flip][:, :, [0, 2, 1]]
        tris.append(tri.reshape(-1, 3))
        node_faces.append(np.repeat(fids, nu * nv))
        tri_faces.append(np.repeat(fids, len(pattern)))
        cells = (nu - 1) * (nv - 1)
        q0u = np.broadcast_to(gu[:, :-1, None], (count, nu - 1, nv - 1)).ravel()
        q1u = np.broadcast_to(gu[:, 1:, None], (count, nu - 1, nv - 1)).ravel()
        q0v = np.broadcast_to(gv[:, None, :-1], (count, nu - 1, nv - 1)).ravel()
        q1v = np.broadcast_to(gv[:, None, 1:], (count, nu - 1, nv - 1)).ravel()
        quad_list.append(np.column_stack([q0u, q1u, q0v, q1v]))
        quad_faces.append(np.repeat(fids, cells))
        offset += count * nu * nv
    uv = np.concatenate(uvs)
    node_face = np.concatenate(node_faces)
    triangles = np.concatenate(tris)
    quads = np.concatenate(quad_list)
    quad_face = np.concatenate(quad_faces)
    triangle_face = np.concatenate(tri_faces)
    # exact area: 2x2 Gauss-Legendre on every grid cell
    g = 0.5 / np.sqrt(3.0)
    mid_u, half_u = 0.5 * (quads[:, 0] + quads[:, 1]), quads[:, 1] - quads[:, 0]
    mid_v, half_v = 0.5 * (quads[:, 2] + quads[:, 3]), quads[:, 3] - quads[:, 2]
    gu = np.concatenate([mid_u - g * half_u, mid_u + g * half_u, mid_u - g * half_u, mid_u + g * half_u])
    gv = np.concatenate([mid_v - g * half_v, mid_v - g * half_v, mid_v + g * half_v, mid_v + g * half_v])
    gauss = sset.evaluate(np.tile(quad_face, 4), gu, gv, order=1)
    jac = np.linalg.norm(np.cross(gauss.du, gauss.dv), axis=1) * np.tile(0.25 * half_u * half_v, 4)
    area = np.bincount(np.tile(quad_face, 4), weights=jac, minlength=len(sset.surfaces))
    return uv, triangles, node_face, triangle_face, area


def grid_tessellation(
    sset: SurfaceSet, faces: list[int], reversed_faces: np.ndarray, tolerances: GridTolerances, count: int
) -> GridTessellation:
    """Grid tessellation of ``faces`` (indices into ``sset``, which holds ``count`` faces).

    A face short of its exact area by more than ``tolerances.allowed_shortfall``
    (a chordal shortfall on a small, tightly curved face) is gridded again, twice
    as fine, up to three times; only those faces are redone. Triangles with an
    edge collapsed to a point (grid rows at a pole) are dropped.
    """
    batches = []
    todo = np.asarray(faces, dtype=np.int64)
    factor = np.ones(count)
    area = np.zeros(count)
    for attempt in range(4):
        uv, tri, nf, tf, batch_area = _grid_pass(sset, todo.tolist(), reversed_faces, tolerances, factor[todo])
        nodes = sset.evaluate(nf, uv[:, 0], uv[:, 1], order=1)
        s, su, sv = nodes.points, nodes.du, nodes.dv
        batches.append((uv, tri, nf, tf, s, su, sv))
        area[todo] = batch_area[todo]
        mesh = np.bincount(tf, weights=triangle_areas(s, tri), minlength=count)[todo]
        exact = area[todo]
        short = (exact > 0) & ((exact - mesh) / np.where(exact > 0, exact, 1.0) > tolerances.allowed_shortfall(exact))
        if not short.any() or attempt == 3:
            break
        todo = todo[short]
        factor[todo] *= 2
    # each face keeps its last gridding
    last = np.full(count, -1)
    for b, batch in enumerate(batches):
        last[np.unique(batch[2])] = b
    parts: list[list[np.ndarray]] = [[] for _ in range(7)]
    offset = 0
    for b, (uv, tri, nf, tf, s, su, sv) in enumerate(batches):
        keep_node = last[nf] == b
        keep_tri = last[tf] == b
        remap = np.cumsum(keep_node) - 1 + offset
        for part, arr in zip(parts, (uv[keep_node], remap[tri[keep_tri]], nf[keep_node], tf[keep_tri],
                                     s[keep_node], su[keep_node], sv[keep_node])):
            part.append(arr)
        offset += int(keep_node.sum())
    uv, tri, nf, tf, s, su, sv = (np.concatenate(part) for part in parts)
    keep = ~_collapsed(s, tri)
    return GridTessellation(uv, tri[keep], nf, tf[keep], area, s, su, sv)


def _collapsed(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(m,) bool: the triangle has an edge of zero length (relative to the points' size)."""
    t = points[triangles]
    scale = 1e-12 * max(1.0, float(np.abs(points).max()))
    dead = np.zeros(len(triangles), dtype=bool)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        dead |= np.linalg.norm(t[:, i] - t[:, j], axis=1) <= scale
    return dead


