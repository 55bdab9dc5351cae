"""Cost that follows the bone, not the mesh (issue 24): vectorised topology, the working copy of a dense
mesh, and the deviation still measured against the full mesh."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

import bonecad
from bonecad.mesh.closest import TriangleLocator
from bonecad.mesh.intake import prepare_bone
from bonecad.mesh.sampling import midpoint_subdivision
from bonecad.mesh.topology import (duplicate_faces, edge_counts, is_closed_and_oriented, merge_duplicate_vertices,
                                   non_manifold_vertices)
from bonecad.mesh.working import simplified, working_triangles

from .conftest import REAL_MESHES, TIBIA_DIR
from .defaults import SETTINGS


def test_merge_matches_meshlab(phantom):
    """Exact duplicates merged into the first (order kept), as MeshLab does: an STL's unshared corners."""
    import pymeshlab

    corners = phantom.vertices[phantom.faces].reshape(-1, 3).astype(np.float32)
    faces = np.arange(len(corners)).reshape(-1, 3)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=corners.astype(np.float64), face_matrix=faces.astype(np.int32)))
    ms.meshing_remove_duplicate_vertices()
    vertices, merged = merge_duplicate_vertices(corners, faces)
    assert np.array_equal(vertices.astype(np.float64), ms.current_mesh().vertex_matrix())
    assert np.array_equal(merged, ms.current_mesh().face_matrix())


def test_equal_rows_exact_under_hash_collisions(monkeypatch):
    """Rows grouped by their hash are regrouped exactly where hashes collide (here: every hash 0), and
    vertices merged exactly (the first of each, in input order)."""
    from bonecad.mesh import topology

    rng = np.random.default_rng(1)
    rows = rng.integers(0, 40, (500, 3)).astype(np.float32)[rng.integers(0, 500, 6000)]
    _, first, inverse = np.unique(rows, axis=0, return_index=True, return_inverse=True)
    firsts = np.sort(first)
    expected = (rows[firsts], np.searchsorted(firsts, first[inverse.ravel()]).reshape(-1, 3))
    for mix in (topology._WORD_MIX, np.zeros(6, dtype=np.uint64)):
        monkeypatch.setattr(topology, "_WORD_MIX", mix)
        assert np.array_equal(topology.first_of_equal_rows(rows), first[inverse.ravel()])
        vertices, faces = merge_duplicate_vertices(rows, np.arange(len(rows)).reshape(-1, 3))
        assert np.array_equal(vertices, expected[0]) and np.array_equal(faces, expected[1])


def test_negative_zero_is_zero():
    """A corner at -0.0 and one at 0.0 are the same vertex (their bits differ), and the input is left as given."""
    corners = np.array([[0.0, 1.0, 2.0], [-0.0, 1.0, 2.0], [1.0, 0.0, 0.0]], dtype=np.float32)
    given = corners.copy()
    vertices, faces = merge_duplicate_vertices(corners, np.array([[0, 1, 2]]))
    assert len(vertices) == 2 and faces.tolist() == [[0, 0, 1]] and not np.signbit(vertices).any()
    assert np.array_equal(corners, given) and np.signbit(corners[1, 0])


def test_equal_rows_split_between_two_processes(monkeypatch):
    """Rows grouped in two halves, one in a forked job: the same first rows as grouped at once, under hash
    collisions too, for floats and integers."""
    from bonecad.mesh import topology
    from bonecad.run.executor import Fork

    rng = np.random.default_rng(2)
    monkeypatch.setattr(topology, "SPLIT_ROWS", 100)
    for rows in (rng.integers(0, 40, (500, 3)).astype(np.float32)[rng.integers(0, 500, 6000)],
                 rng.integers(-5, 5, (300, 3))[rng.integers(0, 300, 4000)]):
        alone = topology.first_of_equal_rows(rows)
        for mix in (topology._WORD_MIX, np.zeros(6, dtype=np.uint64)):
            monkeypatch.setattr(topology, "_WORD_MIX", mix)
            with Fork() as ex:
                assert np.array_equal(topology.first_of_equal_rows(rows, beside=ex.submit), alone)


def _tetrahedron_on(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """A small closed tetrahedron (4 triangles as 12 corners) outside a mesh, touching it at the first corner
    of its first face only: a vertex of two fans, once the corners are merged."""
    a, b, c = vertices[faces[0]]
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal)
    side = (b - a) / np.linalg.norm(b - a)
    points = np.array([a, a + 2 * normal + side, a + 2 * normal + np.cross(normal, side), a + 3 * normal])
    tetra = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    if np.einsum("ij,ij->i", points[tetra[:, 0]], np.cross(points[tetra[:, 1]], points[tetra[:, 2]])).sum() < 0:
        tetra = tetra[:, ::-1]
    return points[tetra].reshape(-1, 3)


@pytest.mark.parametrize("extra", [None, "degenerate face", "pinched vertex"])
def test_cleanup_beside_gives_the_same_bone(dense, monkeypatch, extra):
    """The runner's cleanup, half the merging, the face checks, the vertices' fans and the bodies' measures in
    forked jobs: the same bone, bit for bit, as cleaned in one process, also when a face is dropped (the
    edges counted beside are then not used) and when a vertex joins two fans (the bodies read meanwhile are
    not used: MeshLab repairs the mesh)."""
    from bonecad.mesh import topology
    from bonecad.run.executor import Fork

    monkeypatch.setattr(topology, "SPLIT_ROWS", 1000)
    corners = dense.vertices[dense.faces].reshape(-1, 3).astype(np.float32)  # an STL's unshared corners
    if extra == "pinched vertex":
        corners = np.vstack([corners, _tetrahedron_on(corners, np.arange(3)[None]).astype(np.float32)])
    faces = np.arange(len(corners)).reshape(-1, 3)
    if extra == "degenerate face":
        faces = np.vstack([faces, [0, 0, 1]])

    def cleaned(beside):
        return prepare_bone(corners, faces, source="soup", settings=SETTINGS.mesh, plausible=SETTINGS.units,
                            working_copy=lambda bone, settings, **_: bone, beside=beside)

    alone = cleaned(None)
    with Fork() as ex:
        split = cleaned(ex.submit)
    assert np.array_equal(split.vertices, alone.vertices) and np.array_equal(split.faces, alone.faces)
    assert split.summary() == alone.summary()  # repairs and bodies
    assert any("degenerate" in r for r in alone.repairs) == (extra == "degenerate face")
    assert any("non-manifold vertices" in r for r in alone.repairs) == (extra == "pinched vertex")


def test_edges_fans_and_duplicates():
    sphere = trimesh.creation.icosphere(2)
    faces = np.asarray(sphere.faces)
    edges = edge_counts(faces, len(sphere.vertices))
    assert is_closed_and_oriented(faces) and non_manifold_vertices(faces, edges) == 0
    assert not is_closed_and_oriented(np.vstack([faces[1:], faces[:1, ::-1]]))  # one face turned over
    assert edge_counts(faces[1:], len(sphere.vertices)).border_edges == 3
    # two spheres touching at one vertex: a vertex of two fans
    other = faces + len(sphere.vertices)
    other[other == len(sphere.vertices)] = 0
    pinched = np.vstack([faces, other])
    assert non_manifold_vertices(pinched, edge_counts(pinched, 2 * len(sphere.vertices))) == 1
    assert duplicate_faces(np.vstack([faces, faces[5, [1, 2, 0]]])).tolist() == [False] * len(faces) + [True]


def test_edge_counts_against_their_definition():
    """Each edge's faces, its first two half-edges (increasing) and its orientation, as counted one half-edge at
    a time; the same whether the half-edges' indices fit under the keys (a plain sort) or not (an argsort)."""
    sphere = trimesh.creation.icosphere(2)
    faces = np.asarray(sphere.faces)
    faces = np.vstack([faces[3:], faces[[5, 9]]])  # a hole, edges of three faces
    faces[40] = faces[40, ::-1]  # turned over
    n = len(sphere.vertices)
    halves: dict[tuple[int, int], list[int]] = {}
    for h, (a, b) in enumerate(zip(faces.ravel(), faces[:, [1, 2, 0]].ravel())):
        halves.setdefault((min(a, b), max(a, b)), []).append(h)
    pairs = sorted(halves)
    for vertex_count in (n, 2**31):  # 2^31: keys of 62 bits, no room for the index
        edges = edge_counts(faces, vertex_count)
        assert [(int(k // vertex_count), int(k % vertex_count)) for k in edges.keys] == pairs
        assert edges.faces_per_edge.tolist() == [len(halves[p]) for p in pairs]
        assert edges.half_edges.tolist() == [[halves[p][0], halves[p][min(1, len(halves[p]) - 1)]] for p in pairs]
        forward = faces.ravel() < faces[:, [1, 2, 0]].ravel()
        assert edges.consistent.tolist() == [len(halves[p]) != 2 or forward[halves[p][0]] != forward[halves[p][1]]
                                             for p in pairs]
    assert edges.border_edges > 0 and edges.non_manifold_edges > 0 and not edges.consistent.all()


def test_pinched_mesh_goes_to_meshlab(phantom, tmp_path):
    """A non-manifold vertex (a second body touching the tibia at one vertex) is repaired, and said."""
    ball = trimesh.creation.icosphere(2, radius=5.0)
    top = int(np.argmax(phantom.vertices[:, 2]))
    offset = phantom.vertices[top] - ball.vertices[int(np.argmin(ball.vertices[:, 2]))]
    vertices = np.vstack([phantom.vertices, ball.vertices + offset])
    path = tmp_path / "pinched.stl"
    faces = np.vstack([phantom.faces, ball.faces + len(phantom.vertices)])
    trimesh.Trimesh(vertices, faces, process=False).export(path)
    bone = bonecad.load_bone(path)
    assert any("non-manifold vertices" in r for r in bone.repairs)
    assert bone.watertight


@pytest.fixture(scope="module")
def dense(phantom):
    """The phantom split twice at its edge midpoints (16 times the triangles, the same surface)."""
    vertices, faces = phantom.vertices, phantom.faces
    while working_triangles(vertices, faces, SETTINGS.mesh) is None:
        vertices, faces = midpoint_subdivision(vertices, faces)
    return prepare_bone(vertices, faces, source="dense phantom", settings=SETTINGS.mesh, plausible=SETTINGS.units)


def test_dense_mesh_gets_a_close_working_copy(dense, phantom):
    work = dense.working
    assert work is not None and dense.work is work
    assert work.triangle_count <= working_triangles(dense.vertices, dense.faces, SETTINGS.mesh) * 1.01
    assert is_closed_and_oriented(work.faces)
    measured = TriangleLocator(work.vertices, work.faces).distance(dense.vertices).max()
    assert measured <= SETTINGS.mesh.working_max_deviation_mm
    assert dense.summary()["working_copy"]["max_deviation_mm"] == pytest.approx(measured, abs=1e-4)
    # the anatomy read on the copy is the anatomy of the full mesh
    assert np.allclose(bonecad.anatomical_frame(dense).origin, bonecad.anatomical_frame(phantom).origin, atol=0.3)


def test_deviation_is_measured_against_the_full_mesh(dense, phantom, phantom_frame):
    from dataclasses import replace

    from bonecad.analysis.model import model_deviation, tessellate_model
    from bonecad.contours.curves import contour_curves
    from bonecad.nurbs_model.model import build_nurbs

    model = build_nurbs(contour_curves(phantom, phantom_frame, settings=SETTINGS.curves), settings=SETTINGS.nurbs)
    analysis = replace(SETTINGS.analysis, sample_points=5000)
    deviation = model_deviation(tessellate_model(model.shape, analysis), dense, phantom_frame, analysis)
    assert len(deviation.vertex_deviation_mm) == len(dense.working.vertices)  # the colour map draws the copy
    area = float(dense.face_areas().sum())
    assert deviation.mesh_to_cad.weights.sum() == pytest.approx(area, rel=1e-9)  # samples of the full mesh
    assert TriangleLocator(dense.vertices, dense.faces).distance(deviation.mesh_to_cad.points).max() < 1e-9


def test_simplified_in_passes(dense, monkeypatch):
    """The working copy's simplifier works in passes of at most ``working_pass_reduction`` times fewer triangles
    each, the last to the count asked, the first on the mesh's two halves apart (their cut kept); the result is
    closed and close to the mesh."""
    import fast_simplification

    asked = []
    one_pass = fast_simplification.simplify

    def counted(points, triangles, target_count, preserve_border):
        asked.append((len(triangles), target_count, preserve_border))
        return one_pass(points, triangles, target_count=target_count, preserve_border=preserve_border)

    monkeypatch.setattr(fast_simplification, "simplify", counted)
    reduction = SETTINGS.mesh.working_pass_reduction
    target = dense.triangle_count // 20
    vertices, faces = simplified(dense.vertices, dense.faces, target, pass_reduction=reduction)
    assert [kept for *_, kept in asked] == [True, True, False, False]
    (n_a, t_a, _), (n_b, t_b, _) = asked[:2]
    assert n_a + n_b == dense.triangle_count and abs(n_a - n_b) < 0.01 * n_a  # cut at the median
    assert int(target * reduction**2) - 2 <= t_a + t_b <= int(target * reduction**2)
    assert [t for _, t, _ in asked[2:]] == [int(target * reduction), target]
    assert all(n <= reduction * t for n, t, _ in asked[2:])
    assert len(faces) <= target * 1.01 and is_closed_and_oriented(faces)
    assert TriangleLocator(vertices, faces).distance(dense.vertices).max() < SETTINGS.mesh.working_max_deviation_mm
    asked.clear()
    simplified(dense.vertices, dense.faces, target)
    assert asked == [(dense.triangle_count, target, False)]  # the 3-D view's: one pass


@pytest.mark.skipif(not REAL_MESHES, reason=f"real meshes folder {TIBIA_DIR} is absent")
def test_real_meshes_are_their_own_working_copy():
    """The meshes of ../shared/data are no denser than the working copy: read as they are (same figures)."""
    for path in REAL_MESHES:
        assert bonecad.load_bone(path).working is None, path.name


def test_locator_keeps_the_meshs_normals_and_areas(phantom):
    """The full mesh's vertex normals and triangle areas are computed once with its tree and reused by the
    deviation: the same arrays as computed afresh, and the same samples."""
    from bonecad.analysis.deviation import sample_surface
    from bonecad.mesh.closest import vertex_normals
    from bonecad.mesh.sampling import triangle_areas

    locator = TriangleLocator(phantom.vertices, phantom.faces)
    assert np.array_equal(locator.vertex_normals, vertex_normals(phantom.vertices, phantom.faces))
    assert locator.vertex_normals is locator.vertex_normals  # kept
    assert np.array_equal(locator.triangle_areas, triangle_areas(phantom.vertices, phantom.faces))
    given = sample_surface(phantom.vertices, phantom.faces, 2000, seed=3, areas=locator.triangle_areas)
    afresh = sample_surface(phantom.vertices, phantom.faces, 2000, seed=3)
    assert np.array_equal(given.points, afresh.points) and np.array_equal(given.triangle, afresh.triangle)


def test_copy_made_beside_the_tree(dense):
    """The runner's intake: the working copy simplified in a forked job while the parent builds the full mesh's
    tree; the same copy as made in turn, and the tree kept by the bone's later copies (not pickled)."""
    import pickle
    from dataclasses import replace

    from bonecad.run.executor import executor_for
    from bonecad.run.pipeline import copy_beside_tree

    with executor_for(True) as ex:
        bone = prepare_bone(dense.vertices, dense.faces, source="dense phantom", settings=SETTINGS.mesh,
                            plausible=SETTINGS.units, working_copy=copy_beside_tree(ex))
    assert np.array_equal(bone.work.vertices, dense.work.vertices) and np.array_equal(bone.work.faces,
                                                                                        dense.work.faces)
    (tree,) = [held[2] for held in bone.trees.values()]
    assert bone.locator is tree and replace(bone, repairs=()).locator is tree  # built once, in the intake
    assert replace(bone, vertices=bone.vertices + 1.0).locator is not tree  # other arrays: a tree of their own
    assert bone.locator is tree
    assert pickle.loads(pickle.dumps(bone)).trees == {}


def test_halves_simplified_on_both_cores(dense):
    """A copy of more than one pass: the runner simplifies the first pass's halves in a forked job and in
    the parent, and gets the copy made in turn (bit-equal), closed and close to the mesh."""
    from dataclasses import replace

    from bonecad.mesh.working import pass_targets, with_working_copy
    from bonecad.run.executor import executor_for
    from bonecad.run.pipeline import copy_beside_tree

    settings = replace(SETTINGS.mesh, working_pass_reduction=2.0)
    target = working_triangles(dense.vertices, dense.faces, settings)
    assert target is not None and len(pass_targets(target, dense.triangle_count, 2.0)) == 2
    alone = with_working_copy(replace(dense, working=None), settings).working
    with executor_for(True) as ex:
        work = copy_beside_tree(ex)(replace(dense, working=None), settings).working
    assert alone is not None and work is not None
    assert np.array_equal(work.vertices, alone.vertices) and np.array_equal(work.faces, alone.faces)
    assert is_closed_and_oriented(work.faces) and work.triangle_count <= target * 1.01
    assert work.extra["max_deviation_mm"] <= settings.working_max_deviation_mm


def test_fit_points_of_a_dense_mesh_come_from_a_coarser_copy(dense, phantom_frame):
    """The T-spline fit's points on a dense mesh: the working copy simplified further to triangles of about
    ``fit_copy_edge_mm`` (fewer points than the copy's vertices, the same surface); a mesh as read is used as is."""
    from dataclasses import replace

    from bonecad.mesh.sampling import median_edge_mm, triangle_areas
    from bonecad.mesh.working import coarser_copy
    from bonecad.tspline_model.model import fit_points

    settings = SETTINGS.tspline
    work = dense.work
    vertices, faces = coarser_copy(work.vertices, work.faces, settings.fit_copy_edge_mm)
    area = triangle_areas(work.vertices, work.faces).sum()
    assert abs(len(faces) - area / (np.sqrt(3) / 4 * settings.fit_copy_edge_mm**2)) < 0.02 * len(faces)
    assert len(faces) < 0.8 * work.triangle_count and is_closed_and_oriented(faces)
    assert TriangleLocator(work.vertices, work.faces).distance(vertices).max() < 0.05
    assert coarser_copy(vertices, faces, settings.fit_copy_edge_mm / 2)[1] is faces  # coarse already: itself
    points, weights = fit_points(dense, phantom_frame, settings)
    # (simplified in bone coordinates there: the same copy up to rounding)
    assert abs(len(points) - len(vertices)) < 0.01 * len(vertices) and abs(weights.sum() - area) < 0.01 * area
    assert median_edge_mm(vertices, faces) <= settings.fit_point_spacing_mm
    as_read, _ = fit_points(replace(dense, working=None), phantom_frame, settings)
    assert len(as_read) == len(dense.vertices)
