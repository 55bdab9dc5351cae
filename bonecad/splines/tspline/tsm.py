"""The ``.tsm`` T-spline format (``#TS0200``), read and written; its structural invariants.

The format (no published specification; ``../shared/TSM.md`` gathers what is
known) is a half-edge mesh: faces ``f <link> <flag>``, edges ``e <link>
<knot interval>``, vertices ``v <link> <EAST|NORTH|WEST|SOUTH>``, links
``l <prev> <next> <opp> <origin vertex> <face | -1> <edge> <flag>``,
boundary edges ``ec <edge> 0``, control points ``0g x y z w`` and, in the
Rhino convention, a grip map (``0m odd-grip-map``, ``0m gvp|gv <vertex>``,
``0m cg <vertex> 4 d_N d_W d_S d_E <grips>``) that attaches the second
control row of a clamped cubic boundary to each boundary vertex. A bare
keyword is a deleted slot that keeps its index; records this module does not
know (``100001uv``, ``106ek``, ...) are kept verbatim and skipped.

``TSMDocument`` holds one file; ``parse``/``read`` check it (a malformed
file raises ``TSMError``, an ``InputError`` naming the line and what was
expected), ``format_document``/``write`` write it. ``census`` measures the
invariants of TSM.md section 9 (link identities, closed face loops with four
corners, opposite sides with equal knot-interval sums, boundary flags, Euler
characteristic and boundary loops, star points, signed volume of a closed
cage); ``from_faces`` builds a document from face loops; ``rhino_document``
and ``to_tspline`` convert between bonecad T-splines and the Rhino convention
(clamped boundaries through the grip map, one periodic direction allowed).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from bonecad.errors import InputError
from bonecad.splines.tspline.tmesh import END_LINES, TMesh
from bonecad.splines.tspline.tspline import TSpline

HEADER_LINE = "#TS0200"
#: EAST = +s, NORTH = +t, WEST = -s, SOUTH = -t (quarter turns counter-clockwise from +s)
DIRECTIONS = ("EAST", "NORTH", "WEST", "SOUTH")
#: header keywords, in the order real files write them
HEADER_KEYS = ("degree", "cap-type", "star-smoothness", "units", "force-bezier-end-conditions", "end-conditions",
               "star-knot-rule")
FOOTER_KEYS = ("tol", "geom-tol", "ver", "behavior-version", "compat-version")
#: Fusion's convention (its own read-backs): no grip map, coordinates read as centimetres
FUSION_HEADER = (("degree", "3"), ("cap-type", "G1CAPS"), ("star-smoothness", "0"), ("units", "1 centimeters"),
                 ("end-conditions", "MULTIPLE_KNOTS"), ("star-knot-rule", "NURCCS"))
FUSION_FOOTER = (("tol", "1e-05"), ("geom-tol", "1e-05"), ("ver", "1"))
#: the Rhino T-Splines plugin's convention: clamped (Bezier) boundaries through the grip map, mm
RHINO_HEADER = (("degree", "3"), ("cap-type", "1"), ("star-smoothness", "0"), ("units", "0.001 millimeters"),
                ("force-bezier-end-conditions", "1"))
RHINO_FOOTER = (("tol", "1e-05"), ("ver", "904"))
#: relative tolerance of knot-interval sums (opposite face sides, parameters met along two paths)
INTERVAL_RTOL = 1e-9
_UNIT_MM = {"millimeters": 1.0, "centimeters": 10.0, "meters": 1000.0, "inches": 25.4, "feet": 304.8}


class TSMError(InputError):
    """A malformed ``.tsm`` file: the line (1-based, 0 when none applies) and what was expected there."""

    def __init__(self, line: int, detail: str, path: object | None = None):
        self.line = line
        self.detail = detail
        super().__init__(f"line {line}: {detail}" if line else detail, path)


@dataclass(frozen=True, eq=False)
class TSMDocument:
    """One ``.tsm`` file. Deleted slots have link -1 (links: prev -1).

    header, footer : (keyword, rest of the line) in file order.
    faces : (F, 2) int [link, flag]. edges : (E,) int link; intervals : (E,) float.
    vertices : (V,) int link; directions : (V,) int, index into DIRECTIONS.
    links : (L, 7) int [prev, next, opp, vertex, face, edge, flag].
    edge_conditions : (k, 2) int [edge, value].
    grips : (G, 4) float [x, y, z, w] as written (no unit conversion).
    grip_owner : (G,) int vertex of each grip, grip_primary : (G,) bool (``gvp``), both
        empty without a grip map; compound : ((vertex, (d_N, d_W, d_S, d_E), grips), ...).
    extensions : unknown records, verbatim. record_lines : kind -> (n,) 1-based line of
        each record (all zero for a document built in memory).
    """

    header: tuple[tuple[str, str], ...]
    faces: np.ndarray
    edges: np.ndarray
    intervals: np.ndarray
    vertices: np.ndarray
    directions: np.ndarray
    links: np.ndarray
    edge_conditions: np.ndarray
    grips: np.ndarray
    grip_owner: np.ndarray
    grip_primary: np.ndarray
    compound: tuple[tuple[int, tuple[int, ...], tuple[int, ...]], ...] = ()
    grip_map: bool = False
    extensions: tuple[str, ...] = ()
    footer: tuple[tuple[str, str], ...] = ()
    record_lines: dict[str, np.ndarray] = field(default_factory=dict)

    def setting(self, key: str) -> str | None:
        """The rest of a header line (``units`` -> "1 centimeters"), None when absent."""
        return dict(self.header).get(key)

    def line_of(self, kind: str, index: int) -> int:
        """The file's line number of record ``index`` of ``kind`` (0 when unknown), for error messages."""
        lines = self.record_lines.get(kind)
        return int(lines[index]) if lines is not None and 0 <= index < len(lines) else 0

    @property
    def live_faces(self) -> np.ndarray:
        """Indices of the faces not deleted."""
        return np.flatnonzero(self.faces[:, 0] >= 0)

    @property
    def live_edges(self) -> np.ndarray:
        """Indices of the edges not deleted."""
        return np.flatnonzero(self.edges >= 0)

    @property
    def live_vertices(self) -> np.ndarray:
        """Indices of the vertices not deleted."""
        return np.flatnonzero(self.vertices >= 0)

    @property
    def live_links(self) -> np.ndarray:
        """Indices of the links not deleted."""
        return np.flatnonzero(self.links[:, 0] >= 0)

    def unit_mm(self) -> float:
        """Millimetres per coordinate unit: Fusion (``end-conditions``) reads centimetres whatever
        the ``units`` line says (TSM.md section 7); otherwise the ``units`` line's name."""
        if self.setting("end-conditions") is not None:
            return 10.0
        units = (self.setting("units") or "").split()
        if len(units) == 2 and units[1] in _UNIT_MM:
            return _UNIT_MM[units[1]]
        raise TSMError(0, f"unknown units {self.setting('units')!r}: expected one of {sorted(_UNIT_MM)}")


# ------------------------------------------------------------------ reading
def _number(tokens: list[str], i: int, kind, line: int, what: str):
    try:
        value = kind(tokens[i])
    except (IndexError, ValueError):
        got = tokens[i] if i < len(tokens) else "end of line"
        raise TSMError(line, f"expected {what}, got {got!r}") from None
    if kind is float and not np.isfinite(value):
        raise TSMError(line, f"expected a finite {what}, got {tokens[i]!r}")
    return value


def _fields(tokens: list[str], count: int, line: int, record: str) -> list[str]:
    """The record's operands; trailing ``#`` comments are allowed (GrapeTec's annotated files)."""
    ops = tokens[1:]
    for k, tok in enumerate(ops):
        if tok.startswith("#"):
            ops = ops[:k]
            break
    if len(ops) != count:
        raise TSMError(line, f"expected {count} fields after {tokens[0]!r} ({record}), got {len(ops)}")
    return ops


def parse(text: str, source: object | None = None) -> TSMDocument:
    """A ``#TS0200`` document from its text, checked (see ``check``); TSMError on anything malformed."""
    try:
        return _parse(text)
    except TSMError as exc:
        raise TSMError(exc.line, exc.detail, source) from None


def read(path: str | Path) -> TSMDocument:
    """Read and check a ``.tsm`` file; TSMError (exit 2 in the CLI) names the file and the line."""
    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except OSError as exc:
        raise InputError(f"cannot read T-spline file: {exc.strerror or exc}", path) from exc
    except UnicodeDecodeError as exc:
        raise TSMError(0, f"not UTF-8 text ({exc.reason} at byte {exc.start})", path) from exc
    return parse(text, path)


def _parse(text: str) -> TSMDocument:
    rows = text.splitlines()
    if not rows or rows[0].strip() != HEADER_LINE:
        got = rows[0].strip()[:40] if rows else "an empty file"
        raise TSMError(1, f"expected the header {HEADER_LINE!r}, got {got!r}")
    header: list[tuple[str, str]] = []
    footer: list[tuple[str, str]] = []
    faces: list[tuple[int, int] | None] = []
    edges: list[tuple[int, float] | None] = []
    verts: list[tuple[int, int] | None] = []
    links: list[tuple[int, ...] | None] = []
    conds: list[tuple[int, int]] = []
    grips: list[tuple[float, ...]] = []
    lines: dict[str, list[int]] = {"f": [], "e": [], "v": [], "l": [], "ec": [], "0g": [], "0m": []}
    owner: list[int] = []
    primary: list[bool] = []
    compound: list[tuple[int, tuple[int, ...], tuple[int, ...]]] = []
    grip_map = False
    extensions: list[str] = []
    for number, raw in enumerate(rows[1:], start=2):
        tokens = raw.split()
        if not tokens:
            continue
        key = tokens[0]
        if key in HEADER_KEYS:
            header.append((key, " ".join(tokens[1:])))
            continue
        if key in FOOTER_KEYS:
            footer.append((key, " ".join(tokens[1:])))
            continue
        if footer:
            raise TSMError(number, f"expected only footer lines ({', '.join(FOOTER_KEYS)}) after {footer[0][0]!r}, "
                                   f"got {key!r}")
        if key in ("f", "e", "v", "l") and len(tokens) == 1:  # deleted slot
            lines[key].append(number)
            if key == "f":
                faces.append(None)
            elif key == "e":
                edges.append(None)
            elif key == "v":
                verts.append(None)
            else:
                links.append(None)
            continue
        if key == "f":
            a, b = _fields(tokens, 2, number, "face: link flag")
            faces.append((_number([a], 0, int, number, "a link index"), _number([b], 0, int, number, "a face flag")))
        elif key == "e":
            a, b = _fields(tokens, 2, number, "edge: link knot-interval")
            interval = _number([b], 0, float, number, "a knot interval")
            if interval < 0:
                raise TSMError(number, f"expected a non-negative knot interval, got {b!r}")
            edges.append((_number([a], 0, int, number, "a link index"), interval))
        elif key == "v":
            a, b = _fields(tokens, 2, number, "vertex: link direction")
            if b not in DIRECTIONS:
                raise TSMError(number, f"expected a direction ({'/'.join(DIRECTIONS)}), got {b!r}")
            verts.append((_number([a], 0, int, number, "a link index"), DIRECTIONS.index(b)))
        elif key == "l":
            ops = _fields(tokens, 7, number, "link: prev next opp vertex face edge flag")
            links.append(tuple(_number(ops, k, int, number, name) for k, name in
                               enumerate(("a prev link", "a next link", "an opposite link", "a vertex", "a face",
                                          "an edge", "a link flag"))))
        elif key == "ec":
            ops = _fields(tokens, 2, number, "edge condition: edge value")
            conds.append((_number(ops, 0, int, number, "an edge index"), _number(ops, 1, int, number, "a value")))
        elif key == "0g":
            ops = _fields(tokens, 4, number, "grip: x y z w")
            grips.append(tuple(_number(ops, k, float, number, "a coordinate") for k in range(4)))
            lines["0g"].append(number)
            continue
        elif key == "0m":
            grip_map = True
            kind = tokens[1] if len(tokens) > 1 else ""
            if kind == "odd-grip-map":
                _fields(tokens, 1, number, "grip map declaration")
            elif kind in ("gvp", "gv"):
                ops = _fields(tokens, 2, number, f"grip map {kind}: vertex")
                owner.append(_number(ops, 1, int, number, "a vertex index"))
                primary.append(kind == "gvp")
            elif kind == "cg":
                ops = [t for t in tokens[2:]]
                vertex = _number(ops, 0, int, number, "a vertex index")
                valence = _number(ops, 1, int, number, "a valence")
                if valence != 4:
                    raise TSMError(number, f"expected a compound grip of valence 4, got {valence}")
                d = tuple(_number(ops, 2 + k, int, number, "a row count") for k in range(4))
                count = sum(d[k] * (d[(k + 1) % 4] + 1) for k in range(4))
                if len(ops) != 6 + count:
                    raise TSMError(number, f"expected {count} grip indices for rows {d}, got {len(ops) - 6}")
                compound.append((vertex, d, tuple(_number(ops, 6 + k, int, number, "a grip index")
                                                  for k in range(count))))
            else:
                raise TSMError(number, f"expected a grip map record (odd-grip-map, gvp, gv, cg), got {kind!r}")
            lines["0m"].append(number)
            continue
        else:
            extensions.append(raw.strip())
            continue
        lines[key].append(number)
    if not any(k == "ver" for k, _ in footer):
        raise TSMError(len(rows), "expected the footer (tol ..., ver ...) at the end: the file is truncated")
    if grip_map and len(owner) != len(grips):
        raise TSMError(lines["0m"][-1] if lines["0m"] else len(rows),
                       f"the grip map describes {len(owner)} grips, the file has {len(grips)} (0g lines)")
    doc = TSMDocument(
        header=tuple(header),
        faces=np.array([f if f is not None else (-1, 0) for f in faces], dtype=np.int64).reshape(-1, 2),
        edges=np.array([e[0] if e is not None else -1 for e in edges], dtype=np.int64),
        intervals=np.array([e[1] if e is not None else np.nan for e in edges], dtype=np.float64),
        vertices=np.array([v[0] if v is not None else -1 for v in verts], dtype=np.int64),
        directions=np.array([v[1] if v is not None else -1 for v in verts], dtype=np.int64),
        links=np.array([x if x is not None else (-1,) * 7 for x in links], dtype=np.int64).reshape(-1, 7),
        edge_conditions=np.array(conds, dtype=np.int64).reshape(-1, 2),
        grips=np.array(grips, dtype=np.float64).reshape(-1, 4),
        grip_owner=np.array(owner, dtype=np.int64),
        grip_primary=np.array(primary, dtype=bool),
        compound=tuple(compound),
        grip_map=grip_map,
        extensions=tuple(extensions),
        footer=tuple(footer),
        record_lines={k: np.array(v, dtype=np.int64) for k, v in lines.items()},
    )
    check(doc)
    return doc


# ---------------------------------------------------------------- checking
def _face_loops(doc: TSMDocument) -> dict[int, list[int]]:
    """Links of each live face in loop order from its ``f`` link (assumes checked references)."""
    loops = {}
    nxt = doc.links[:, 1]
    for f in doc.live_faces:
        start = int(doc.faces[f, 0])
        loop = [start]
        k = int(nxt[start])
        while k != start and len(loop) <= len(doc.links):
            loop.append(k)
            k = int(nxt[k])
        loops[int(f)] = loop
    return loops


def _sides(doc: TSMDocument, loop: list[int]) -> list[list[int]]:
    """A face loop cut into sides at its corner links (flag 0): lists of links."""
    flags = doc.links[loop, 6]
    first = int(np.flatnonzero(flags == 0)[0])
    order = loop[first:] + loop[:first]
    sides: list[list[int]] = []
    for k in order:
        if doc.links[k, 6] == 0:
            sides.append([])
        sides[-1].append(k)
    return sides


def check(doc: TSMDocument) -> None:
    """Raise TSMError (with the record's line) unless the document is a well-formed T-mesh:
    references in range and live, the link identities, closed face loops with four corners,
    equal knot-interval sums on opposite sides, one grip per vertex (or a complete grip map)."""
    L, F, E, V = len(doc.links), len(doc.faces), len(doc.edges), len(doc.vertices)
    live_l = doc.links[:, 0] >= 0
    if not live_l.any():
        raise TSMError(0, "expected links (l records), the file has none")

    def ref(kind: str, index: int, target: str, value: int, count: int, live: np.ndarray, allow_outside=False):
        if allow_outside and value == -1:
            return
        if not 0 <= value < count:
            raise TSMError(doc.line_of(kind, index), f"{target} {value} is not defined (the file has {count})")
        if not live[value]:
            raise TSMError(doc.line_of(kind, index), f"{target} {value} is a deleted slot")

    live_f, live_e, live_v = doc.faces[:, 0] >= 0, doc.edges >= 0, doc.vertices >= 0
    for f in doc.live_faces:
        ref("f", f, "link", int(doc.faces[f, 0]), L, live_l)
    for e in doc.live_edges:
        ref("e", e, "link", int(doc.edges[e]), L, live_l)
    for v in doc.live_vertices:
        ref("v", v, "link", int(doc.vertices[v]), L, live_l)
    names = ("prev link", "next link", "opposite link")
    for i in doc.live_links:
        p, n, o, v, f, e, _ = (int(x) for x in doc.links[i])
        for name, value in zip(names, (p, n, o)):
            ref("l", i, name, value, L, live_l)
        ref("l", i, "vertex", v, V, live_v)
        ref("l", i, "face", f, F, live_f, allow_outside=True)
        ref("l", i, "edge", e, E, live_e)
    lk = doc.links
    idx = doc.live_links
    checks = (
        (lk[lk[idx, 0], 1] != idx, "next(prev(link)) is not the link"),
        (lk[lk[idx, 1], 0] != idx, "prev(next(link)) is not the link"),
        (lk[lk[idx, 2], 2] != idx, "opp(opp(link)) is not the link"),
        (lk[idx, 2] == idx, "the link is its own opposite"),
        (lk[lk[idx, 2], 3] != lk[lk[idx, 1], 3], "the opposite link does not start where the next one does"),
        (lk[lk[idx, 2], 5] != lk[idx, 5], "the opposite link belongs to another edge"),
        (lk[lk[idx, 1], 4] != lk[idx, 4], "the next link belongs to another face"),
    )
    for bad, problem in checks:
        if bad.any():
            i = int(idx[np.argmax(bad)])
            raise TSMError(doc.line_of("l", i), f"link {i}: {problem}")
    for e in doc.live_edges:
        owner = doc.links[doc.edges[e]]
        if owner[5] != e:
            raise TSMError(doc.line_of("e", e), f"edge {e}: its link {doc.edges[e]} belongs to edge {owner[5]}")
    per_edge = np.bincount(lk[idx, 5], minlength=E)
    if np.any(per_edge[live_e] != 2):
        e = int(np.flatnonzero(live_e & (per_edge != 2))[0])
        raise TSMError(doc.line_of("e", e), f"edge {e}: expected two links, found {per_edge[e]}")
    for v in doc.live_vertices:
        if lk[doc.vertices[v], 3] != v:
            raise TSMError(doc.line_of("v", v), f"vertex {v}: its link {doc.vertices[v]} starts at vertex "
                                                f"{lk[doc.vertices[v], 3]}")
    for f in doc.live_faces:
        start = int(doc.faces[f, 0])
        if lk[start, 4] != f:
            raise TSMError(doc.line_of("f", f), f"face {f}: its link {start} belongs to face {lk[start, 4]}")
    loops = _face_loops(doc)
    for f, loop in loops.items():
        corners = int(np.sum(lk[loop, 6] == 0))
        if corners != 4:
            raise TSMError(doc.line_of("f", f), f"face {f}: expected 4 corner links (flag 0), found {corners}")
        sums = [float(doc.intervals[lk[side, 5]].sum()) for side in _sides(doc, loop)]
        scale = max(max(sums), 1e-300)
        for a, b in ((0, 2), (1, 3)):
            if abs(sums[a] - sums[b]) > INTERVAL_RTOL * scale:
                raise TSMError(doc.line_of("f", f), f"face {f}: inconsistent knot intervals, opposite sides sum to "
                                                    f"{sums[a]!r} and {sums[b]!r}")
    in_face = np.zeros(L, dtype=bool)
    for loop in loops.values():
        in_face[loop] = True
    stray = live_l & (lk[:, 4] >= 0) & ~in_face
    if stray.any():
        i = int(np.flatnonzero(stray)[0])
        raise TSMError(doc.line_of("l", i), f"link {i} claims face {lk[i, 4]} but is not on that face's loop")
    for k, (edge, _value) in enumerate(doc.edge_conditions):
        ref("ec", k, "edge", int(edge), E, live_e)
    _check_grips(doc)


def _check_grips(doc: TSMDocument) -> None:
    V, G = len(doc.vertices), len(doc.grips)
    live_v = doc.vertices >= 0
    if not doc.grip_map:
        if G != int(live_v.sum()):
            line = int(doc.record_lines["0g"][-1]) if len(doc.record_lines.get("0g", [])) else 0
            raise TSMError(line, f"expected one grip (0g) per vertex without a grip map: {int(live_v.sum())} "
                                 f"vertices, {G} grips")
    else:
        for k, v in enumerate(doc.grip_owner):
            if not (0 <= v < V and live_v[v]):
                raise TSMError(doc.line_of("0m", k), f"grip {k} belongs to vertex {v}, which is not defined")
        per_vertex = np.bincount(doc.grip_owner[doc.grip_primary], minlength=V)
        if np.any(per_vertex[live_v] != 1):
            v = int(np.flatnonzero(live_v & (per_vertex != 1))[0])
            raise TSMError(0, f"vertex {v}: expected one primary grip (0m gvp), found {per_vertex[v]}")
        for vertex, _d, grips in doc.compound:
            for g in grips:
                if not 0 <= g < G or doc.grip_owner[g] != vertex or doc.grip_primary[g]:
                    raise TSMError(0, f"compound grip of vertex {vertex}: grip {g} is not one of its secondary grips")
    if G and np.any(doc.grips[:, 3] <= 0):
        g = int(np.flatnonzero(doc.grips[:, 3] <= 0)[0])
        raise TSMError(int(doc.record_lines["0g"][g]) if "0g" in doc.record_lines and len(doc.record_lines["0g"])
                       else 0, f"grip {g}: expected a positive weight, got {doc.grips[g, 3]!r}")


@dataclass(frozen=True)
class Census:
    """Counts and invariants of a checked document (TSM.md section 9).

    euler : V - E + F. boundary_loops : loops of outside (face -1) links.
    star_points : interior vertices of valence != 4 that are no T-junction.
    t_junctions : vertices that some face passes straight through (a flag-1 link leaves them).
    bad_boundary_flags : boundary links whose flag is not 3 - (quarter turns of the faces at
        their origin). boundary_edges_match_ec : the ``ec`` edges are exactly the boundary edges.
    signed_volume : of the control cage (fan-triangulated faces), for closed cages; 0 when open.
    """

    faces: int
    edges: int
    vertices: int
    euler: int
    boundary_loops: int
    star_points: tuple[int, ...]
    valences: dict[int, int]
    t_junctions: int
    bad_boundary_flags: int
    boundary_edges_match_ec: bool
    signed_volume: float

    @property
    def closed(self) -> bool:
        return self.boundary_loops == 0


def census(doc: TSMDocument) -> Census:
    """Measure the document's invariants (it must have passed ``check``)."""
    lk = doc.links
    idx = doc.live_links
    origin = lk[idx, 3]
    V = len(doc.vertices)
    valence = np.bincount(origin, minlength=V)
    outside = idx[lk[idx, 4] < 0]
    inside = idx[lk[idx, 4] >= 0]
    t_junction = np.zeros(V, dtype=bool)
    t_junction[lk[inside[lk[inside, 6] == 1], 3]] = True
    on_boundary = np.zeros(V, dtype=bool)
    on_boundary[lk[outside, 3]] = True
    live_v = doc.vertices >= 0
    star = np.flatnonzero(live_v & ~on_boundary & ~t_junction & (valence != 4))
    quarter = np.bincount(lk[inside, 3], weights=np.where(lk[inside, 6] == 0, 1, 2), minlength=V)
    bad_flags = int(np.sum(lk[outside, 6] != 3 - quarter[lk[outside, 3]]))
    seen = np.zeros(len(lk), dtype=bool)
    loops = 0
    for k in outside:
        if seen[k]:
            continue
        loops += 1
        j = int(k)
        while not seen[j]:
            seen[j] = True
            j = int(lk[j, 1])
    ec = set(doc.edge_conditions[:, 0].tolist())
    volume = 0.0
    if loops == 0 and not doc.grip_map:
        points = np.zeros((V, 3))
        points[doc.live_vertices] = doc.grips[:, :3]
        for loop in _face_loops(doc).values():
            p = points[lk[loop, 3]]
            volume += float(np.einsum("ij,ij->", p[0][None], np.cross(p[1:-1], p[2:]))) / 6.0
    star_valences = {int(v): int(valence[v]) for v in star}
    return Census(
        faces=len(doc.live_faces), edges=len(doc.live_edges), vertices=int(live_v.sum()),
        euler=int(live_v.sum()) - len(doc.live_edges) + len(doc.live_faces), boundary_loops=loops,
        star_points=tuple(int(v) for v in star), valences=star_valences, t_junctions=int(t_junction.sum()),
        bad_boundary_flags=bad_flags, boundary_edges_match_ec=ec == set(lk[outside, 5].tolist()),
        signed_volume=volume,
    )


# ---------------------------------------------------------------- writing
def _real(x: float) -> str:
    """Shortest round-trip decimal (Rhino's style): reading it back gives the same double."""
    return repr(float(x))


def format_document(doc: TSMDocument) -> str:
    """The document as ``#TS0200`` text (LF line ends)."""
    out = [HEADER_LINE, ""]
    out += [f"{k} {v}" for k, v in doc.header]
    out += ["f" if f[0] < 0 else f"f {f[0]} {f[1]}" for f in doc.faces.tolist()]
    out += ["e" if link < 0 else f"e {link} {_real(iv)}" for link, iv in zip(doc.edges.tolist(), doc.intervals)]
    out += ["v" if link < 0 else f"v {link} {DIRECTIONS[d]}" for link, d in zip(doc.vertices.tolist(),
                                                                                 doc.directions.tolist())]
    out += ["l" if row[0] < 0 else "l " + " ".join(map(str, row)) for row in doc.links.tolist()]
    out += [f"ec {e} {c}" for e, c in doc.edge_conditions.tolist()]
    if doc.grip_map:
        out.append("0m odd-grip-map")
        out += [f"0m {'gvp' if p else 'gv'} {v}" for v, p in zip(doc.grip_owner.tolist(), doc.grip_primary.tolist())]
        out += [f"0m cg {v} 4 {' '.join(map(str, d))} {' '.join(map(str, g))}".rstrip() for v, d, g in doc.compound]
    out += ["0g " + " ".join(_real(x) for x in row) for row in doc.grips]
    out += list(doc.extensions)
    out.append("")
    out += [f"{k} {v}" for k, v in doc.footer]
    return "\n".join(out) + "\n"


def write(doc: TSMDocument, path: str | Path) -> Path:
    """Write the document (it is checked first: a malformed document is a bug, ValueError)."""
    try:
        check(doc)
    except TSMError as exc:
        raise ValueError(f"refusing to write a malformed T-spline document: {exc}") from exc
    path = Path(path)
    path.write_text(format_document(doc))
    return path


def from_faces(
    loops: list[list[int]],
    corners: list[list[bool]],
    directions: list[list[int]],
    intervals: dict[tuple[int, int], float],
    grips: np.ndarray,
    *,
    header: tuple[tuple[str, str], ...],
    footer: tuple[tuple[str, str], ...],
) -> TSMDocument:
    """A document from face loops over vertices 0..V-1.

    loops : per face, its vertices counter-clockwise in (s, t) seen from outside (the first
        one a corner). corners : per face and vertex, whether the loop turns there (flag 0).
    directions : per face and vertex, the direction index (DIRECTIONS) of the link leaving it.
    intervals : knot interval of each edge, keyed by (min vertex, max vertex).
    grips : (V, 4) control points [x, y, z, w], one per vertex (no grip map).
    Boundary links (face -1) close every open side; edges are numbered in order of their
    first link, like Fusion does; each vertex's link is its first outgoing link.
    """
    prev: list[int] = []
    nxt: list[int] = []
    origin: list[int] = []
    face: list[int] = []
    flag: list[int] = []
    direc: list[int] = []
    for f, (loop, corner, dirs) in enumerate(zip(loops, corners, directions)):
        base = len(origin)
        n = len(loop)
        for k in range(n):
            prev.append(base + (k - 1) % n)
            nxt.append(base + (k + 1) % n)
            origin.append(loop[k])
            face.append(f)
            flag.append(0 if corner[k] else 1)
            direc.append(dirs[k])
    n_face_links = len(origin)
    by_pair: dict[tuple[int, int], int] = {}
    for i in range(n_face_links):
        pair = (origin[i], origin[nxt[i]])
        if pair in by_pair:
            raise ValueError(f"the directed edge {pair} appears in two faces (inconsistent orientation)")
        by_pair[pair] = i
    opp = [-1] * n_face_links
    boundary = []
    for i in range(n_face_links):
        a, b = origin[i], origin[nxt[i]]
        j = by_pair.get((b, a))
        if j is None:
            boundary.append(i)
        else:
            opp[i] = j
    # boundary links: from b to a for each unpaired face link a -> b; chained along the outside
    start_of = {}
    for i in boundary:
        j = len(origin)
        a, b = origin[i], origin[nxt[i]]
        prev.append(-1)
        nxt.append(-1)
        origin.append(b)
        face.append(-1)
        flag.append(0)
        direc.append((direc[i] + 2) % 4)
        opp.append(i)
        opp[i] = j
        if b in start_of:
            raise ValueError(f"vertex {b} starts two boundary links (a pinched boundary)")
        start_of[b] = j
    quarter: dict[int, int] = {}
    for i in range(n_face_links):
        quarter[origin[i]] = quarter.get(origin[i], 0) + (1 if flag[i] == 0 else 2)
    for j in range(n_face_links, len(origin)):
        end = origin[opp[j]]  # the boundary link b -> a ends where its face link starts
        k = start_of[end]
        nxt[j] = k
        prev[k] = j
        flag[j] = 3 - quarter[origin[j]]
    edge_of = [-1] * len(origin)
    edges: list[int] = []
    values: list[float] = []
    for i in range(len(origin)):
        if edge_of[i] < 0:
            edge_of[i] = edge_of[opp[i]] = len(edges)
            edges.append(i)
            a, b = origin[i], origin[opp[i]]
            values.append(float(intervals[(min(a, b), max(a, b))]))
    n_vertices = len(grips)
    vertex_link = [-1] * n_vertices
    for i in range(len(origin)):
        if vertex_link[origin[i]] < 0:
            vertex_link[origin[i]] = i
    if min(vertex_link) < 0:
        raise ValueError(f"vertex {vertex_link.index(-1)} is on no face")
    links = np.stack([prev, nxt, opp, origin, face, edge_of, flag], axis=1).astype(np.int64)
    outside_edges = sorted({edge_of[j] for j in range(n_face_links, len(origin))})
    doc = TSMDocument(
        header=header,
        faces=np.column_stack([np.cumsum([0] + [len(x) for x in loops[:-1]]), np.zeros(len(loops))]).astype(np.int64),
        edges=np.array(edges, dtype=np.int64),
        intervals=np.array(values, dtype=np.float64),
        vertices=np.array(vertex_link, dtype=np.int64),
        directions=np.array([direc[i] for i in vertex_link], dtype=np.int64),
        links=links,
        edge_conditions=np.array([[e, 0] for e in outside_edges], dtype=np.int64).reshape(-1, 2),
        grips=np.asarray(grips, dtype=np.float64),
        grip_owner=np.zeros(0, dtype=np.int64),
        grip_primary=np.zeros(0, dtype=bool),
        footer=footer,
    )
    return doc


# ------------------------------------------------------- bonecad T-splines
def grid_faces(s_edges: np.ndarray, t_edges: np.ndarray, periodic: bool) -> tuple[np.ndarray, np.ndarray]:
    """Faces and vertices of a T-mesh given by its edge arrays (``TMesh`` layout, any sub-grid).

    s_edges : (T, Ns) bool, t_edges : (S, T - 1) bool (Ns = S when ``periodic``, else S - 1).
    Returns ((n_f, 4) int [i0, i1, j0, j1] of each face, i1 unwrapped past S when it
    crosses the periodic seam; (S, T) bool vertex mask). Zero-width strips are faces too.
    """
    from bonecad.splines.tspline.extraction import _last_at_or_before, _next_after
    from bonecad.splines.tspline.tmesh import _neighbour_flags

    s_n, t_n = t_edges.shape[0], s_edges.shape[0]
    n_cells = s_n if periodic else s_n - 1
    left = _last_at_or_before(t_edges[:n_cells], periodic) % s_n  # (Ns, T-1)
    bottom = _last_at_or_before(s_edges[: t_n - 1], False).T  # (Ns, T-1)
    jj = np.broadcast_to(np.arange(t_n - 1), left.shape)
    key = left * t_n + bottom[left % n_cells, jj]
    keys, inverse = np.unique(key, return_inverse=True)
    i0, j0 = keys // t_n, keys % t_n
    i1 = _next_after(t_edges, periodic)[i0, j0]
    j1 = _next_after(s_edges, False)[j0, i0 % n_cells]
    if np.any(np.bincount(inverse.ravel(), minlength=len(keys)) != (i1 - i0) * (j1 - j0)):
        raise ValueError("the T-mesh has a face that is not a rectangle")
    l_s, r_s = _neighbour_flags(s_edges, periodic)
    d_t, u_t = _neighbour_flags(t_edges, False)
    vertices = (l_s | r_s).T & (d_t | u_t)
    return np.stack([i0, i1, j0, j1], axis=1), vertices


def _mesh_document(s_edges, t_edges, periodic, s_values, t_values, grips_of, *, header, footer):
    """A document from a T-mesh (edge arrays over lines with values ``s_values`` (unwrapped
    by the caller's period), ``t_values``); ``grips_of(vertex index array (n, 2))`` -> (n, 4)."""
    faces, vmask = grid_faces(s_edges, t_edges, periodic)
    s_n = t_edges.shape[0]
    jj, ii = np.nonzero(vmask.T)
    ids = -np.ones(vmask.shape, dtype=np.int64)
    ids[ii, jj] = np.arange(len(ii))
    loops, corners, dirs = [], [], []
    intervals: dict[tuple[int, int], float] = {}

    def side(points, direction):
        keep = [(i, j) for i, j in points if vmask[i % s_n, j]]
        return keep, [direction] * len(keep)

    for i0, i1, j0, j1 in faces.tolist():
        sides = [side([(i, j0) for i in range(i0, i1)], 0), side([(i1, j) for j in range(j0, j1)], 1),
                 side([(i, j1) for i in range(i1, i0, -1)], 2), side([(i0, j) for j in range(j1, j0, -1)], 3)]
        pts = [p for pts, _ in sides for p in pts]
        loop = [int(ids[i % s_n, j]) for i, j in pts]
        corner = [(i, j) in ((i0, j0), (i1, j0), (i1, j1), (i0, j1)) for i, j in pts]
        loops.append(loop)
        corners.append(corner)
        dirs.append([d for _, ds in sides for d in ds])
        for k in range(len(pts)):
            a, b = pts[k], pts[(k + 1) % len(pts)]
            va, vb = loop[k], loop[(k + 1) % len(pts)]
            value = abs(s_values(b[0]) - s_values(a[0])) if a[1] == b[1] else abs(t_values[b[1]] - t_values[a[1]])
            intervals[(min(va, vb), max(va, vb))] = float(value)
    grips = grips_of(np.stack([ii, jj], axis=1))
    return from_faces(loops, corners, dirs, intervals, grips, header=header, footer=footer), np.stack([ii, jj], axis=1)


def _vertex_lines(mesh: TMesh) -> tuple[slice, slice]:
    """The lines that carry TSM vertices: a clamped end's two control rows share one vertex line
    (the inner one, END_LINES - 1); periodic s keeps every line."""
    s_n, t_n = mesh.shape
    e = END_LINES - 1
    return (slice(0, s_n) if mesh.periodic else slice(e, s_n - e)), slice(e, t_n - e)


def rhino_document(ts: TSpline) -> TSMDocument:
    """The T-spline in the Rhino convention: clamped boundaries written with
    ``force-bezier-end-conditions 1`` and the grip map (each boundary vertex's primary grip is its
    end control point, its secondary grips the second control rows), grips in anchor order, mm.
    """
    mesh = ts.mesh
    s_sl, t_sl = _vertex_lines(mesh)
    s_n, t_n = mesh.shape
    s_edges = mesh.s_edges[t_sl] if mesh.periodic else mesh.s_edges[t_sl, s_sl.start: s_sl.stop - 1]
    t_edges = mesh.t_edges[s_sl, t_sl.start: t_sl.stop - 1]
    s0, t0 = s_sl.start, t_sl.start
    anchor_id = {(int(i), int(j)): k for k, (i, j) in enumerate(mesh.anchors)}
    compound = []
    blocks: dict[int, list[int]] = {}

    def grips_of(vertices: np.ndarray) -> np.ndarray:
        for v, (i, j) in enumerate(vertices.tolist()):
            i, j = i + s0, j + t0
            i_out = i if mesh.periodic or END_LINES - 1 < i < s_n - END_LINES else (i - 1 if i < s_n // 2 else i + 1)
            j_out = j if END_LINES - 1 < j < t_n - END_LINES else (j - 1 if j < t_n // 2 else j + 1)
            d = [int(j_out < j), int(i_out > i), int(j_out > j), int(i_out < i)]  # rows to the N, W, S, E
            blocks[v] = [anchor_id[(i_out, j_out)]] + [anchor_id[(i_out + dx, j_out + dy)] for dx, dy in _wedges(d)]
            compound.append((v, tuple(d)))
        return np.zeros((len(vertices), 4))

    doc, _ = _mesh_document(s_edges, t_edges, mesh.periodic, lambda i: mesh.s_value(i + s0), mesh.t_lines[t0:],
                            grips_of, header=RHINO_HEADER, footer=RHINO_FOOTER)
    grip_vertex = np.empty(ts.n_control, dtype=np.int64)
    is_primary = np.zeros(ts.n_control, dtype=bool)
    for v, anchors in blocks.items():
        grip_vertex[anchors] = v
        is_primary[anchors[0]] = True
    if sorted(a for anchors in blocks.values() for a in anchors) != list(range(ts.n_control)):
        raise ValueError("the T-mesh's anchors do not map one to one onto TSM vertices and their grip blocks")
    cg = tuple((v, d, tuple(blocks[v][1:])) for v, d in compound if any(d))
    grips = np.hstack([ts.control_points, ts.weights[:, None]])
    return replace(doc, grips=grips, grip_owner=grip_vertex, grip_primary=is_primary, compound=cg, grip_map=True)


def _wedges(d) -> list[tuple[int, int]]:
    """Grid offsets (ds, dt) of a compound grip block's grips, in the file's order, for rows
    d = (N, W, S, E) in the vertex's frame (TSM.md section 5; 0 or 1 rows per side)."""
    n, w, s, e = d
    out = [(-c, r) for r in range(1, n + 1) for c in range(w + 1)]
    out += [(-c, -r) for c in range(1, w + 1) for r in range(s + 1)]
    out += [(c, -r) for r in range(1, s + 1) for c in range(e + 1)]
    out += [(c, r) for c in range(1, e + 1) for r in range(n + 1)]
    return out


def _link_directions(doc: TSMDocument, loops: dict[int, list[int]]) -> np.ndarray:
    """Global direction (0..3) of every live link: face 0's ``f`` side runs EAST, each face turns
    left at its corners, opposite links point the other way. TSMError when no such field exists
    (star points, or a non-orientable mesh)."""
    lk = doc.links
    side_of = np.full(len(lk), -1, dtype=np.int64)
    for loop in loops.values():
        k = 0
        for link in loop:
            if lk[link, 6] == 0 and link != loop[0]:
                k += 1
            side_of[link] = k
    direction = np.full(len(lk), -1, dtype=np.int64)
    base = {}
    order = sorted(loops)
    if not order:
        raise TSMError(0, "expected faces (f records), the file has none")
    pending = [order[0]]
    base[order[0]] = 0
    while pending:
        f = pending.pop()
        for link in loops[f]:
            d = (base[f] + side_of[link]) % 4
            direction[link] = d
            o = int(lk[link, 2])
            g = int(lk[o, 4])
            want = (d + 2) % 4
            if g < 0:
                direction[o] = want
                continue
            if g not in base:
                base[g] = (want - side_of[o]) % 4
                pending.append(g)
            elif (base[g] + side_of[o]) % 4 != want:
                raise TSMError(doc.line_of("l", o), f"link {o}: the faces around it admit no consistent (s, t) "
                                                    "directions (a star point or a twisted mesh)")
    if len(base) != len(loops):
        raise TSMError(0, "the T-mesh is not connected: bonecad reads one surface per file")
    return direction


def _parameters(doc: TSMDocument, direction: np.ndarray) -> tuple[np.ndarray, float | None, int]:
    """(V, 2) (s, t) of every vertex from the knot intervals; the period and its axis (0 s, 1 t)
    when one direction closes on itself, else (None, -1)."""
    lk = doc.links
    step = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
    V = len(doc.vertices)
    param = np.full((V, 2), np.nan)
    outgoing: dict[int, list[int]] = {}
    for i in doc.live_links:
        outgoing.setdefault(int(lk[i, 3]), []).append(int(i))
    start = int(doc.live_vertices[0])
    param[start] = 0.0
    stack = [start]
    while stack:
        v = stack.pop()
        for i in outgoing.get(v, []):
            w = int(lk[lk[i, 2], 3])
            if np.isnan(param[w, 0]):
                param[w] = param[v] + doc.intervals[lk[i, 5]] * step[direction[i]]
                stack.append(w)
    idx = doc.live_links
    end = lk[lk[idx, 2], 3]
    gap = param[end] - param[lk[idx, 3]] - doc.intervals[lk[idx, 5]][:, None] * step[direction[idx]]
    scale = max(float(np.nanmax(np.abs(param))), 1e-300)
    tol = INTERVAL_RTOL * scale
    off = np.abs(gap) > tol
    if not off.any():
        return param, None, -1
    axes = np.flatnonzero(off.any(axis=0))
    if len(axes) > 1:
        raise TSMError(0, "the T-mesh closes on itself in both directions (a torus): bonecad reads open patches "
                          "and tubes periodic in one direction")
    axis = int(axes[0])
    period = float(np.min(np.abs(gap[off[:, axis], axis])))
    multiples = gap[:, axis] / period
    if np.any(np.abs(multiples - np.round(multiples)) * period > tol):
        i = int(idx[np.argmax(np.abs(multiples - np.round(multiples)))])
        raise TSMError(doc.line_of("l", i), f"link {i}: knot intervals disagree around the mesh")
    return param, period, axis


def _lines(values: np.ndarray, period: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Distinct knot values (clustered within the interval tolerance) and each value's line index."""
    if period is not None:
        values = np.mod(values, period)
    order = np.argsort(values, kind="stable")
    span = max(float(np.ptp(values)), period or 0.0, 1e-300)
    new = np.concatenate([[True], np.diff(values[order]) > INTERVAL_RTOL * span])
    line = np.empty(len(values), dtype=np.int64)
    line[order] = np.cumsum(new) - 1
    distinct = values[order][new]
    if period is not None and len(distinct) > 1 and distinct[-1] > period * (1 - INTERVAL_RTOL):
        line[line == len(distinct) - 1] = 0
        distinct = distinct[:-1]
    return distinct, line


def to_tspline(doc: TSMDocument) -> TSpline:
    """The document as a bonecad T-spline (mm), where bonecad's T-spline rules apply: no star
    points, one rectangular (or periodic-in-one-direction) domain, clamped boundaries given by the
    Rhino grip map. TSMError says which rule the file breaks."""
    info = census(doc)
    if info.star_points:
        v = info.star_points[0]
        raise TSMError(doc.line_of("v", v), f"{len(info.star_points)} star point(s) (vertex {v} has valence "
                                            f"{info.valences[v]}): bonecad evaluates T-splines without "
                                            "extraordinary points only")
    if info.closed:
        raise TSMError(0, "a closed T-mesh without star points (a torus): bonecad reads open patches and tubes")
    if not doc.grip_map:
        raise TSMError(0, "open boundaries without a grip map (Fusion's MULTIPLE_KNOTS end condition, whose "
                          "boundary rule is unpublished): bonecad reads clamped boundaries in the Rhino "
                          "convention (force-bezier-end-conditions 1, 0m grip map)")
    loops = _face_loops(doc)
    direction = _link_directions(doc, loops)
    param, period, axis = _parameters(doc, direction)
    if axis == 1:  # bonecad's periodic direction is s: turn the frame a quarter (orientation kept)
        direction = np.where(direction >= 0, (direction + 3) % 4, -1)
        param, period, axis = _parameters(doc, direction)
    live = doc.live_vertices
    s_vals, s_line = _lines(param[live, 0], period)
    t_vals, t_line = _lines(param[live, 1], None)
    t_vals = t_vals - t_vals[0]
    e = END_LINES - 1
    periodic = period is not None
    if periodic:
        s_lines, si = s_vals - s_vals[0], s_line
    else:
        s_vals = s_vals - s_vals[0]
        s_lines, si = np.concatenate([[0.0] * e, s_vals, [s_vals[-1]] * e]), s_line + e
    t_lines, tj = np.concatenate([[0.0] * e, t_vals, [t_vals[-1]] * e]), t_line + e
    s_n, t_n = len(s_lines), len(t_lines)
    vi = np.full(len(doc.vertices), -1, dtype=np.int64)
    vj = np.full(len(doc.vertices), -1, dtype=np.int64)
    vi[live], vj[live] = si, tj
    s_edges = np.zeros((t_n, s_n if periodic else s_n - 1), dtype=bool)
    t_edges = np.zeros((s_n, t_n - 1), dtype=bool)
    lk = doc.links
    for edge in doc.live_edges:
        link = int(doc.edges[edge])
        d = int(direction[link])
        a, b = int(lk[link, 3]), int(lk[lk[link, 2], 3])
        if d in (2, 3):
            a, b, d = b, a, d - 2
        if d == 0:
            lo, hi = vi[a], vi[b]
            if periodic:
                hi = hi if hi > lo else hi + s_n
                s_edges[vj[a], np.arange(lo, hi) % s_n] = True
            else:
                s_edges[vj[a], lo:hi] = True
        else:
            t_edges[vi[a], vj[a]:vj[b]] = True
    # the clamped ends: four complete boundary lines, crossing edges run through the zero-width strip
    s_edges[:e], s_edges[t_n - e:] = True, True
    t_edges[:, :e] = t_edges[:, e: e + 1]
    t_edges[:, t_n - 1 - e:] = t_edges[:, t_n - 2 - e: t_n - 1 - e]
    if not periodic:
        t_edges[: e + 1], t_edges[s_n - e - 1:] = True, True
        s_edges[:, :e] = s_edges[:, e: e + 1]
        s_edges[:, s_n - 1 - e:] = s_edges[:, s_n - 2 - e: s_n - 1 - e]
    try:
        mesh = TMesh(s_lines, t_lines, s_edges, t_edges, period)
        mesh.validate()
    except ValueError as exc:
        raise TSMError(0, f"not a T-mesh bonecad can evaluate: {exc}") from None
    anchor_id = {(int(i), int(j)): k for k, (i, j) in enumerate(mesh.anchors)}
    grip_anchor = np.full(len(doc.grips), -1, dtype=np.int64)
    offsets = {v: [(0, 0)] for v in live.tolist()}
    vertex_dir = doc.directions
    for vertex, d_local, grips in doc.compound:
        turn = (int(direction[doc.vertices[vertex]]) - int(vertex_dir[vertex])) % 4
        if max(d_local) > 1:
            raise TSMError(0, f"compound grip of vertex {vertex}: more than one extra row per side (degree 3 "
                              "clamped boundaries have one)")
        offsets[vertex] = [(0, 0)] + [_turn(o, turn) for o in _wedges(d_local)]
        if len(grips) != len(offsets[vertex]) - 1:
            raise TSMError(0, f"compound grip of vertex {vertex}: {len(grips)} grips for rows {d_local}")
    primary = {int(v): g for g, v in enumerate(doc.grip_owner) if doc.grip_primary[g]}
    for v in live.tolist():
        i, j = vi[v], vj[v]
        i_out = i if periodic or e < i < s_n - END_LINES else (i - 1 if i == e else i + 1)
        j_out = j if e < j < t_n - END_LINES else (j - 1 if j == e else j + 1)
        block = [primary[v]] + [g for vertex, _, grips in doc.compound if vertex == v for g in grips]
        for g, (dx, dy) in zip(block, offsets[v]):
            key = (int(i_out + dx) % s_n if periodic else int(i_out + dx), int(j_out + dy))
            if key not in anchor_id:
                raise TSMError(doc.line_of("0g", g), f"grip {g} of vertex {v} lands on no control point of the "
                                                     "clamped T-mesh")
            grip_anchor[g] = anchor_id[key]
    if np.any(grip_anchor < 0) or len(set(grip_anchor.tolist())) != len(mesh.anchors):
        raise TSMError(0, f"the grip map does not give each of the {len(mesh.anchors)} control points of the "
                          f"clamped T-mesh exactly one of the {len(doc.grips)} grips")
    points = np.empty((len(mesh.anchors), 3))
    weights = np.empty(len(mesh.anchors))
    points[grip_anchor] = doc.grips[:, :3] * doc.unit_mm()
    weights[grip_anchor] = doc.grips[:, 3]
    return TSpline(mesh, points, weights)


def _turn(offset: tuple[int, int], quarter_turns: int) -> tuple[int, int]:
    dx, dy = offset
    for _ in range(quarter_turns):
        dx, dy = -dy, dx
    return dx, dy


def read_tspline(path: str | Path) -> TSpline:
    """A ``.tsm`` file as a bonecad T-spline (mm): ``read`` then ``to_tspline`` (the file's name on errors)."""
    doc = read(path)
    try:
        return to_tspline(doc)
    except TSMError as exc:
        raise TSMError(exc.line, exc.detail, path) from None


def write_tspline(ts: TSpline, path: str | Path) -> Path:
    """A bonecad T-spline (mm) as a Rhino-convention ``.tsm`` file (clamped boundaries, grip map, mm)."""
    return write(rhino_document(ts), path)
