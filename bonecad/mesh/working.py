"""The working copy of a dense bone mesh: the same surface in as many triangles as the tolerance needs.

A mesh whose triangles are far smaller than the tolerance asks for (0.3 mm CT,
subdivided exports) carries no more shape, but every stage that reads it pays
for each triangle. Such a mesh gets a copy simplified by quadric edge collapse
(Garland & Heckbert 1997, in the Fast-Quadric-Mesh-Simplification library
through ``fast_simplification``) to triangles of about ``working_edge_mm``, in
passes of at most ``working_pass_reduction`` times fewer triangles each;
the largest distance of the full mesh's vertices from the copy is measured
on every run and held below ``working_max_deviation_mm`` (the copy gets more
triangles otherwise). The deviation of the models is measured against the full mesh.
The first of several passes simplifies the mesh's two halves apart (``halves``), so that
the runner gives them both cores: TLEM2's tibia split 16-fold (1.40 M triangles) to 122 k,
1.74 + 1.41 s CPU for the halves against 3.27 s for the whole, the copy's worst vertex
0.0144 mm from the mesh against 0.0120 mm.

Vertex clustering on a grid before the simplifier (to let it see fewer
triangles) was measured and dropped: on TLEM2 split 64-fold (5.6 M
triangles) cells of 0.2 / 0.3 mm left 2.0 M / 1.0 M triangles and cut the
simplification from 19 to 7.5 / 3.0 s CPU, but the clustered mesh was no
longer closed (triangles folded over, sheets merged in a cell) and the copy
lay 0.29 / 0.44 mm from the mesh at its worst vertex (bound 0.1 mm).
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from bonecad.mesh.bone_mesh import BoneMesh
from bonecad.mesh.closest import TriangleLocator
from bonecad.mesh.sampling import triangle_areas
from bonecad.mesh.topology import first_of_equal_rows, is_closed_and_oriented, merge_duplicate_vertices
from bonecad.settings import MeshSettings

log = logging.getLogger(__name__)

#: area (mm^2) of an equilateral triangle of edge 1 mm
_UNIT_TRIANGLE_MM2 = np.sqrt(3.0) / 4.0


def working_triangles(vertices: np.ndarray, faces: np.ndarray, settings: MeshSettings, *,
                      area_mm2: float | None = None) -> int | None:
    """Triangles of the working copy of a mesh (equilateral ones of ``working_edge_mm`` over its area), or
    None when the mesh has at most ``working_density_factor`` times as many (it is its own working copy).

    area_mm2 : the mesh's area when the caller has it (None: summed here)."""
    area = float(triangle_areas(vertices, faces).sum()) if area_mm2 is None else area_mm2
    target = int(np.ceil(area / (_UNIT_TRIANGLE_MM2 * settings.working_edge_mm**2)))
    return target if len(faces) > settings.working_density_factor * target else None


def pass_targets(triangles: int, faces: int, pass_reduction: float | None) -> list[int]:
    """The triangle counts of ``simplified``'s passes from ``faces`` triangles, first to last (the last
    ``triangles``), each at most ``pass_reduction`` times fewer than the one before (None: one pass)."""
    targets = [int(triangles)]
    while pass_reduction is not None and targets[-1] * pass_reduction < faces:
        targets.append(int(targets[-1] * pass_reduction))
    return targets[::-1]


def simplified_once(vertices: np.ndarray, faces: np.ndarray, target: int, *, keep_border: bool = False
                    ) -> tuple[np.ndarray, np.ndarray]:
    """One pass of quadric edge collapse to about ``target`` triangles (vertices mm, faces).

    keep_border : no edge with a vertex on the mesh's border collapses (a half's cut, ``halves``).
    An edge collapse can leave two faces on the same three vertices (a fin of
    no volume, one in a million): both are dropped, with the vertices no face uses.
    """
    import fast_simplification

    points, kept = fast_simplification.simplify(np.ascontiguousarray(vertices, dtype=np.float64),
                                                np.ascontiguousarray(faces, dtype=np.int64), target_count=int(target),
                                                preserve_border=keep_border)
    first = first_of_equal_rows(np.sort(kept, axis=1))
    kept = kept[np.bincount(first, minlength=len(kept))[first] == 1]
    used = np.zeros(len(points), dtype=bool)
    used[kept] = True
    return np.asarray(points[used], dtype=np.float64), (np.cumsum(used) - 1)[kept].astype(np.int64)


def halves(vertices: np.ndarray, faces: np.ndarray, target: int
           ) -> tuple[tuple[np.ndarray, np.ndarray, int], tuple[np.ndarray, np.ndarray, int]]:
    """The mesh cut in two at the median of its triangles' centres along its longest extent (a long bone:
    across its shaft), each half with its share of ``target``: (vertices, faces, target) twice.

    A first pass simplifies the halves apart (on two cores, ``simplified_once`` with ``keep_border``, so
    the cut's vertices stay where they are and the halves join again, ``joined``); the next pass
    simplifies the dense ring the cut left with the rest.
    """
    axis = int(np.argmax(np.ptp(vertices, axis=0)))
    centre = vertices[faces[:, 0], axis] + vertices[faces[:, 1], axis] + vertices[faces[:, 2], axis]
    low = centre <= np.median(centre)
    parts = []
    for side in (low, ~low):
        part = faces[side]
        used = np.zeros(len(vertices), dtype=bool)
        used[part] = True
        parts.append((vertices[used], (np.cumsum(used) - 1)[part], int(target * len(part) / len(faces))))
    return parts[0], parts[1]


def joined(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Two simplified halves (vertices, faces) as one mesh, the vertices of their cut merged (bit-equal: the
    first pass kept them)."""
    return merge_duplicate_vertices(np.concatenate([a[0], b[0]]), np.concatenate([a[1], b[1] + len(a[0])]))


def halves_simplified(vertices: np.ndarray, faces: np.ndarray, target: int, *,
                      beside: Callable[..., Any] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The first of several passes: the mesh's two ``halves`` simplified apart towards ``target`` and
    ``joined``. beside : runs the first half's ``simplified_once`` elsewhere (an executor's ``submit``: a
    job with ``result()``) while this process simplifies the second; None: both here, in turn."""
    first, second = halves(vertices, faces, target)
    elsewhere = beside(simplified_once, *first, keep_border=True) if beside is not None else None
    done = simplified_once(*second, keep_border=True)
    return joined(elsewhere.result() if elsewhere is not None else simplified_once(*first, keep_border=True), done)


def coarser_copy(vertices: np.ndarray, faces: np.ndarray, edge_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """A working copy simplified further, in one pass, to equilateral triangles of about ``edge_mm`` over its
    area (vertices mm, faces); the copy itself when it has no more triangles than that."""
    target = int(np.ceil(float(triangle_areas(vertices, faces).sum()) / (_UNIT_TRIANGLE_MM2 * edge_mm**2)))
    return (vertices, faces) if len(faces) <= target else simplified_once(vertices, faces, target)


def first_pass_target(vertices: np.ndarray, faces: np.ndarray, settings: MeshSettings, *,
                      area_mm2: float | None = None) -> int | None:
    """The triangles of the first pass towards the working copy when it takes more than one
    (``halves_simplified``), else None."""
    target = working_triangles(vertices, faces, settings, area_mm2=area_mm2)
    targets = pass_targets(target, len(faces), settings.working_pass_reduction) if target else []
    return targets[0] if len(targets) > 1 else None


def simplified(vertices: np.ndarray, faces: np.ndarray, triangles: int, *, pass_reduction: float | None = None,
               first: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The mesh simplified by quadric edge collapse to about ``triangles`` triangles (vertices mm, faces).

    pass_reduction : simplify in passes (``pass_targets``); None: in one pass. With more than one, the
        first pass simplifies the mesh's two halves apart (``halves_simplified``).
    first : the first pass's result when the caller made it (its halves on two cores), the same as here.
    """
    targets = pass_targets(triangles, len(faces), pass_reduction)
    if len(targets) > 1:
        vertices, faces = first if first is not None else halves_simplified(vertices, faces, targets[0])
        targets = targets[1:]
    for target in targets:
        vertices, faces = simplified_once(vertices, faces, target)
    return vertices, faces


def with_working_copy(bone: BoneMesh, settings: MeshSettings, *, area_mm2: float | None = None,
                      first: tuple[np.ndarray, np.ndarray] | None = None) -> BoneMesh:
    """``bone`` with its working copy (``BoneMesh.working``) when it is denser than the settings need.

    The copy's ``extra`` holds its largest vertex distance from the full mesh
    (``max_deviation_mm``, measured over every vertex of the full mesh).
    area_mm2 : the mesh's area when the caller has it (None: summed here).
    first : ``simplified``'s first pass towards ``working_triangles``, when the caller made it.
    """
    target = working_triangles(bone.vertices, bone.faces, settings, area_mm2=area_mm2)
    while target is not None:
        vertices, faces = simplified(bone.vertices, bone.faces, target,
                                     pass_reduction=settings.working_pass_reduction, first=first)
        first = None  # (a second try starts from the mesh)
        closed = is_closed_and_oriented(faces)
        worst = float(TriangleLocator(vertices, faces).distance(bone.vertices).max()) if closed else np.inf
        if worst <= settings.working_max_deviation_mm:
            break
        log.info("a working copy of %d triangles %s: doubling it", len(faces),
                 f"lies {worst:.3f} mm from the mesh" if closed else "is not closed")
        target *= 2
        if bone.triangle_count <= settings.working_density_factor * target:
            target = None
    if target is None:
        return bone
    log.info("working copy: %d of %d triangles, vertices of the mesh within %.3f mm of it", len(faces),
             bone.triangle_count, worst)
    working = BoneMesh(vertices=vertices, faces=faces, source=bone.source, units=bone.units,
                       watertight=bone.watertight, extra={"max_deviation_mm": round(worst, 4)})
    return replace(bone, working=working)
