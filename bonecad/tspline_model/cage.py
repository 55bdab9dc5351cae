"""The T-spline model as one closed ``.tsm`` control cage in Fusion's convention.

The cage is the tube's T-mesh (every control row, T-junctions and knot
intervals as they are) closed at each end by its apex cap, as one half-edge
mesh of sphere topology:

- the tube's two control rows at a clamped end share a knot value: the edge
  between them has knot interval 0 (a multiple knot, ``end-conditions
  MULTIPLE_KNOTS``); the cap's second row meets the tube's ring row with
  interval 0 as well, so along a meridian the ring is a triple knot (the C0
  joint of the tube and the cap, which is G1 by the cap's construction);
- each cap contributes two rings of control points (its rows 2 and 1, on the
  cap's s-lines: the tube's ring lines plus the cut points below, inserted
  into the cap exactly by knot insertion) and one pole vertex;
- the pole closes the inner ring with four quad faces, like Fusion's own
  capped cylinder: the pole has valence 4 and four ring vertices at odd
  eighths of the period are corners of valence 3 (Fusion's star points); the
  other inner-ring vertices sit on straight sides of those faces (T-junctions).
  Spokes have knot interval period / 8, so every face's opposite sides sum
  equally.

bonecad's caps are tensor-product patches whose pole row degenerates to one
point; Fusion evaluates the four faces round each pole with its own
star-point rules (``cap-type G1CAPS``, ``star-knot-rule NURCCS``, unpublished),
so the surface differs from bonecad's there, inside the caps only.
Coordinates are written in centimetres (Fusion reads them so).
"""
from __future__ import annotations

import numpy as np

from bonecad.splines.tspline import KnotSegment, TSpline, insert_segments
from bonecad.splines.tspline.tsm import FUSION_FOOTER, FUSION_HEADER, TSMDocument, from_faces, grid_faces

#: pole faces per cap (the pole's valence)
POLE_FACES = 4
#: millimetres per coordinate unit of a Fusion .tsm (Fusion reads centimetres)
FUSION_UNIT_MM = 10.0


def _with_cuts(cap: TSpline) -> TSpline:
    """The cap with s-lines at every eighth of the period from its first line (exact knot insertion;
    lines already within 1e-9 of the period are reused)."""
    mesh = cap.mesh
    period = mesh.s_period
    if period is None:
        raise ValueError("a cap must be periodic in s")
    cuts = mesh.s_lines[0] + np.arange(2 * POLE_FACES) * (period / (2 * POLE_FACES))
    new = [float(c) for c in cuts if np.min(np.abs(mesh.s_lines - c)) > 1e-9 * period]
    if not new:
        return cap
    return insert_segments(cap, [KnotSegment("s", c, 0.0, 1.0) for c in new]).tspline


def fusion_cage(tube: TSpline, distal_cap: TSpline, proximal_cap: TSpline) -> TSMDocument:
    """The closed cage of a tube (periodic in s, clamped in t; mm) and its two caps (periodic in s,
    one Bezier span in r; the distal cap's r runs from its pole to the ring, the proximal cap's from
    the ring to its pole, as ``caps.build_cap`` makes them), with outward faces, in Fusion's
    convention (cm)."""
    mesh = tube.mesh
    s_n, t_n = mesh.shape
    period = mesh.s_period
    if period is None:
        raise ValueError("the tube must be periodic in s")
    # the tube: every control row (t-lines 2 .. T-3); its vertices are its anchors, in order
    lo, hi = 2, t_n - 2
    faces, vmask = grid_faces(mesh.s_edges[lo:hi], mesh.t_edges[:, lo: hi - 1], True)
    ids = -np.ones(vmask.shape, dtype=np.int64)
    jj, ii = np.nonzero(vmask.T)
    ids[ii, jj] = np.arange(len(ii))
    points = [tube.control_points]
    weights = [tube.weights]
    loops, corners, dirs = [], [], []
    intervals: dict[tuple[int, int], float] = {}

    def add(loop: list[int], corner: list[bool], direction: list[int], lengths: list[float]) -> None:
        loops.append(loop)
        corners.append(corner)
        dirs.append(direction)
        for k, value in enumerate(lengths):  # the tube's own intervals (written first) are kept exactly
            a, b = loop[k], loop[(k + 1) % len(loop)]
            intervals.setdefault((min(a, b), max(a, b)), float(value))

    t_vals = mesh.t_lines[lo:hi]
    for i0, i1, j0, j1 in faces.tolist():
        pts = ([(i, j0, 0) for i in range(i0, i1)] + [(i1, j, 1) for j in range(j0, j1)]
               + [(i, j1, 2) for i in range(i1, i0, -1)] + [(i0, j, 3) for j in range(j1, j0, -1)])
        pts = [p for p in pts if vmask[p[0] % s_n, p[1]]]
        loop = [int(ids[i % s_n, j]) for i, j, _ in pts]
        nxt = pts[1:] + pts[:1]
        lengths = [mesh.s_value(b[0]) - mesh.s_value(a[0]) if a[2] in (0, 2) else t_vals[b[1]] - t_vals[a[1]]
                   for a, b in zip(pts, nxt)]
        add(loop, [(i, j) in ((i0, j0), (i1, j0), (i1, j1), (i0, j1)) for i, j, _ in pts], [d for *_, d in pts],
            [abs(x) for x in lengths])
    count = len(ii)
    for end, cap in (("distal", distal_cap), ("proximal", proximal_cap)):
        cap = _with_cuts(cap)
        cm = cap.mesh
        lines = cm.s_lines
        m = len(lines)
        rows = cap.control_points[np.lexsort((cm.anchors[:, 0], cm.anchors[:, 1]))].reshape(4, m, 3)
        w_rows = cap.weights[np.lexsort((cm.anchors[:, 0], cm.anchors[:, 1]))].reshape(4, m)
        order = (3, 2, 1, 0) if end == "distal" else (0, 1, 2, 3)  # ring', row 2, row 1, pole
        ring_j = 0 if end == "distal" else len(t_vals) - 1
        ring_i = np.flatnonzero(vmask[:, ring_j])
        ring_s = mesh.s_value(ring_i)
        at = np.searchsorted(lines, ring_s)
        at = np.where((at < m) & (np.abs(lines[np.minimum(at, m - 1)] - ring_s) <= 1e-9 * period), at, at - 1)
        if np.any(np.abs(lines[at] - ring_s) > 1e-9 * period):
            raise ValueError(f"the {end} cap's s-lines do not contain the tube's ring lines")
        row2 = count + np.arange(m)
        row1 = row2 + m
        pole = count + 2 * m
        count = pole + 1
        points += [rows[order[1]], rows[order[2]], rows[order[3]][:1]]
        weights += [w_rows[order[1]], w_rows[order[2]], w_rows[order[3]][:1]]
        ring = [int(ids[i, ring_j]) for i in ring_i]
        gaps = np.diff(np.append(lines, lines[0] + period))
        spoke = period / (2 * POLE_FACES)
        for k in range(len(ring)):  # zero-width strip between the ring row and the cap's row 2
            a, b = at[k], at[(k + 1) % len(ring)]
            span = [(a + x) % m for x in range((b - a) % m + 1 if (b - a) % m else m + 1)]
            inner = [int(row2[c]) for c in span]
            arc = [float(gaps[c]) for c in span[:-1]]
            corner = [True] + [False] * (len(inner) - 2) + [True]
            if end == "distal":
                add(inner + [ring[(k + 1) % len(ring)], ring[k]], corner + [True, True],
                    [0] * (len(inner) - 1) + [1, 2, 3], arc + [0.0, float(sum(arc)), 0.0])
            else:
                add([ring[k], ring[(k + 1) % len(ring)]] + inner[::-1], [True, True] + corner,
                    [0, 1] + [2] * (len(inner) - 1) + [3], [float(sum(arc)), 0.0] + arc[::-1] + [0.0])
        for c in range(m):  # quads between the cap's rows 2 and 1
            d = (c + 1) % m
            if end == "distal":
                add([int(row1[c]), int(row1[d]), int(row2[d]), int(row2[c])], [True] * 4, [0, 1, 2, 3],
                    [gaps[c], spoke, gaps[c], spoke])
            else:
                add([int(row2[c]), int(row2[d]), int(row1[d]), int(row1[c])], [True] * 4, [0, 1, 2, 3],
                    [gaps[c], spoke, gaps[c], spoke])
        cut = np.array([int(np.argmin(np.abs(lines - (lines[0] + x * spoke)))) for x in range(2 * POLE_FACES)])
        for k in range(POLE_FACES):
            p0, q, p1 = cut[2 * k], cut[2 * k + 1], cut[(2 * k + 2) % len(cut)]
            span = [(p0 + x) % m for x in range((p1 - p0) % m + 1)]
            arc = [float(gaps[c]) for c in span[:-1]]
            ring1 = [int(row1[c]) for c in span]
            corner = [c in (p0, q, p1) for c in span]
            if end == "distal":
                iq = span.index(q)
                add([pole] + ring1[::-1], [True] + corner[::-1], [1] + [2] * (len(span) - 1 - iq) + [3] * iq + [0],
                    [spoke] + arc[::-1] + [spoke])
            else:
                add(ring1 + [pole], corner + [True], [0] * span.index(q) + [1] * (len(span) - 1 - span.index(q))
                    + [2, 3], arc + [spoke, spoke])
    grips = np.hstack([np.vstack(points) / FUSION_UNIT_MM, np.concatenate(weights)[:, None]])
    doc = from_faces(loops, corners, dirs, intervals, grips, header=FUSION_HEADER, footer=FUSION_FOOTER)
    if _signed_volume(doc) < 0:  # the frame is left-handed: mirror s (reverse every loop)
        mirror = (2, 1, 0, 3)
        flipped = [[loop[0]] + loop[:0:-1] for loop in loops]
        flipped_corners = [[c[0]] + c[:0:-1] for c in corners]
        # the reversed link b -> a runs against a -> b; s turns round
        flipped_dirs = [[mirror[(x + 2) % 4] for x in d[::-1]] for d in dirs]
        doc = from_faces(flipped, flipped_corners, flipped_dirs, intervals, grips, header=FUSION_HEADER,
                         footer=FUSION_FOOTER)
    return doc


def _signed_volume(doc: TSMDocument) -> float:
    """Signed volume (cm^3) enclosed by the cage's faces, fan-triangulated (positive: outward)."""
    from bonecad.splines.tspline.tsm import census

    return census(doc).signed_volume


def model_cage(model) -> TSMDocument:
    """The Fusion cage of a ``TSplineModel`` in its scanner coordinates (cm)."""
    from bonecad.tspline_model.model import to_scanner

    caps = {cap.end: to_scanner(cap.tspline, model.frame) for cap in model.caps}
    return fusion_cage(to_scanner(model.tspline, model.frame), caps["distal"], caps["proximal"])
