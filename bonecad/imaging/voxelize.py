"""Partial-volume voxelisation of a closed triangle mesh on an axis-aligned grid.

For each of the three grid axes, rays through the voxel centres of every grid
column cross the surface; each crossing enters (+1) or leaves (-1) the solid
according to the sign of the triangle normal along the ray, so the signed
count is the winding number and nested or several bodies need no sorting. The
exact crossing positions give, per voxel, the share of each of its rays that
lies inside. A voxel is crossed by n x n parallel rays per axis (at the
centres of an n x n split of its face); their shares, averaged over the rays
and the three axes, are its partial-volume occupancy in [0, 1]. With one ray
(the centre line) two thirds of the share jump where the surface crosses the
voxel's centre (a plane normal to x: the y and z rays are wholly in or out),
a partial volume far steeper than the voxel's true share. Everything is
vectorised over (triangle, column) pairs.
"""
from __future__ import annotations

import numpy as np


def occupancy(
    vertices: np.ndarray,
    faces: np.ndarray,
    origin: np.ndarray,
    spacing_mm: float | np.ndarray,
    shape: tuple[int, int, int],
    *,
    rays: int = 1,
) -> np.ndarray:
    """(nz, ny, nx) float32 share of each voxel inside the mesh.

    vertices : (n, 3) float, mm; faces : (m, 3) int, outward normals
    origin : (3,) world (x, y, z) of voxel [0, 0, 0]'s centre, mm
    spacing_mm : voxel edge, mm: one for a cubic grid or (x, y, z) for an
        anisotropic one (the shares are taken in voxel units, where every
        voxel is a unit cube); shape : (nz, ny, nx)
    rays : rays per voxel edge across each ray direction (n x n rays per voxel
        and axis; the time grows as n squared)
    """
    spacing = np.broadcast_to(np.asarray(spacing_mm, dtype=np.float64), (3,))
    vertices = (np.asarray(vertices, dtype=np.float64) - np.asarray(origin, dtype=np.float64)) / spacing
    faces = np.asarray(faces, dtype=np.int64)
    if rays < 1:
        raise ValueError(f"rays must be at least 1, got {rays}")
    total = np.zeros(shape, dtype=np.float32)
    offsets = (np.arange(rays) + 0.5) / rays - 0.5  # ray positions across a voxel, voxel units
    # Grid axis a of the (x, y, z) world is array axis 2 - a.
    for ray_axis in range(3):
        total += _axis_occupancy(vertices, faces, shape, ray_axis, offsets)
    total /= 3.0 * rays**2
    np.clip(total, 0.0, 1.0, out=total)
    return total


def _axis_occupancy(grid_vertices: np.ndarray, faces: np.ndarray, shape: tuple[int, int, int],
                    ray_axis: int, offsets: np.ndarray) -> np.ndarray:
    """Sum over the rays of each voxel's inside share along rays parallel to world axis ``ray_axis``, the rays
    offset from the voxel's centre by every pair of ``offsets`` across (vertices and offsets in voxel units)."""
    nxyz = (shape[2], shape[1], shape[0])
    u_axis, v_axis = [a for a in range(3) if a != ray_axis]
    n_ray = nxyz[ray_axis]
    # Difference array in (ray, u, v) layout, one extra cell along the ray; every ray adds to it.
    dims = (n_ray + 1, nxyz[u_axis], nxyz[v_axis])
    flats, weights = [], []
    for du in offsets:
        for dv in offsets:
            shift = np.zeros(3)
            shift[u_axis], shift[v_axis] = du, dv
            kc, frac, s, qu, qv = _crossings(grid_vertices - shift, faces, nxyz, ray_axis)
            flat = (kc * dims[1] + qu) * dims[2] + qv
            flats += [flat, flat + dims[1] * dims[2]]
            weights += [s * frac, s * (1.0 - frac)]
    delta = np.bincount(np.concatenate(flats), weights=np.concatenate(weights), minlength=dims[0] * dims[1] * dims[2])
    cover = np.cumsum(delta.reshape(dims)[:-1], axis=0, dtype=np.float64).astype(np.float32)
    # (ray, u, v) world axes -> array (z, y, x) = world axes (2, 1, 0).
    world_order = (ray_axis, u_axis, v_axis)
    return np.ascontiguousarray(np.transpose(cover, [world_order.index(a) for a in (2, 1, 0)]))


def _crossings(grid_vertices: np.ndarray, faces: np.ndarray, nxyz: tuple[int, int, int], ray_axis: int
               ) -> tuple[np.ndarray, ...]:
    """Where the rays through the voxel centres along ``ray_axis`` cross the surface: per crossing the voxel
    index along the ray, the share of that voxel beyond the crossing, the sign (+1 entering), and the ray's
    (u, v) column (vertices in voxel units)."""
    u_axis, v_axis = [a for a in range(3) if a != ray_axis]
    tri = grid_vertices[faces]  # (m, 3, 3) in voxel units
    pu, pv = tri[:, :, u_axis], tri[:, :, v_axis]
    area2 = (pu[:, 1] - pu[:, 0]) * (pv[:, 2] - pv[:, 0]) - (pu[:, 2] - pu[:, 0]) * (pv[:, 1] - pv[:, 0])
    keep = area2 != 0.0
    tri, pu, pv, area2 = tri[keep], pu[keep], pv[keep], area2[keep]
    # Make every projected triangle counter-clockwise for the coverage test.
    cw = area2 < 0
    pu[cw] = pu[cw][:, [0, 2, 1]]
    pv[cw] = pv[cw][:, [0, 2, 1]]
    # Crossing direction: +1 where the (3-D) normal points against the ray.
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    sign = -np.sign(normal[:, ray_axis])

    u_lo = np.maximum(np.ceil(pu.min(axis=1)), 0).astype(np.int64)
    u_hi = np.minimum(np.floor(pu.max(axis=1)), nxyz[u_axis] - 1).astype(np.int64)
    v_lo = np.maximum(np.ceil(pv.min(axis=1)), 0).astype(np.int64)
    v_hi = np.minimum(np.floor(pv.max(axis=1)), nxyz[v_axis] - 1).astype(np.int64)
    nu = np.maximum(u_hi - u_lo + 1, 0)
    nv = np.maximum(v_hi - v_lo + 1, 0)
    counts = nu * nv
    pair_tri = np.repeat(np.arange(len(counts)), counts)
    start = np.cumsum(counts) - counts
    local = np.arange(len(pair_tri)) - start[pair_tri]
    qu = (u_lo[pair_tri] + local // nv[pair_tri]).astype(np.float64)
    qv = (v_lo[pair_tri] + local % nv[pair_tri]).astype(np.float64)

    inside = np.ones(len(pair_tri), dtype=bool)
    for e in range(3):
        au, av = pu[pair_tri, e], pv[pair_tri, e]
        bu, bv = pu[pair_tri, (e + 1) % 3], pv[pair_tri, (e + 1) % 3]
        du, dv = bu - au, bv - av
        w = du * (qv - av) - dv * (qu - au)
        # Points exactly on an edge belong to one of the two triangles sharing it.
        owns = (dv > 0) | ((dv == 0) & (du > 0))
        inside &= (w > 0) | ((w == 0) & owns)
    pair_tri, qu, qv = pair_tri[inside], qu[inside], qv[inside]

    p0 = tri[pair_tri, 0]
    n = normal[pair_tri]
    crossing = p0[:, ray_axis] - (n[:, u_axis] * (qu - p0[:, u_axis])
                                  + n[:, v_axis] * (qv - p0[:, v_axis])) / n[:, ray_axis]
    s = sign[pair_tri]
    # Voxel kc spans [kc - 0.5, kc + 0.5); it gets the share above the crossing,
    # every voxel beyond it the whole step.
    kc = np.floor(crossing + 0.5)
    frac = kc + 0.5 - crossing
    below = kc < 0
    kc[below], frac[below] = 0.0, 1.0
    keep = kc < nxyz[ray_axis]
    kc, frac, s = kc[keep].astype(np.int64), frac[keep], s[keep]
    return kc, frac, s, qu[keep].astype(np.int64), qv[keep].astype(np.int64)
