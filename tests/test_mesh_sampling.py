"""Fit samples of a mesh: midpoint subdivision keeps the surface and carries per-vertex figures over."""
import numpy as np
import trimesh

from bonecad.mesh.sampling import edge_midpoints, fit_samples, median_edge_mm, midpoint_subdivision, vertex_areas


def _sphere(subdivisions: int = 1):
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=10.0)
    return np.asarray(m.vertices), np.asarray(m.faces)


def test_midpoint_subdivision_keeps_the_surface_and_names_each_new_vertex_s_edge():
    vertices, faces = _sphere()
    new_v, new_f = midpoint_subdivision(vertices, faces)
    assert len(new_f) == 4 * len(faces)
    assert np.isclose(vertex_areas(new_v, new_f).sum(), vertex_areas(vertices, faces).sum(), rtol=1e-12)
    n = len(vertices)
    assert np.array_equal(new_v[:n], vertices)
    # every new vertex is the midpoint of an original edge
    edges = np.unique(np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    assert np.allclose(new_v[n:], 0.5 * (vertices[edges[:, 0]] + vertices[edges[:, 1]]))
    # a closed mesh stays closed: every edge has two faces
    assert trimesh.Trimesh(new_v, new_f, process=False).is_watertight
    assert np.isclose(median_edge_mm(new_v, new_f), 0.5 * median_edge_mm(vertices, faces), rtol=0.05)


def test_fit_samples_take_a_fine_mesh_s_vertices_and_a_coarse_one_s_edge_midpoints_after_splitting():
    vertices, faces = _sphere()
    edge = median_edge_mm(vertices, faces)
    area = vertex_areas(vertices, faces).sum()
    # fine: the vertices, a third of their triangles' area each
    same, same_weights = fit_samples(vertices, faces, edge * 1.01)
    assert np.array_equal(same, vertices) and np.allclose(same_weights, vertex_areas(vertices, faces))
    # coarse, but edges within twice the spacing: the midpoints of the mesh's own edges
    points, weights = fit_samples(vertices, faces, edge * 0.6)
    assert len(points) == 3 * len(faces) // 2
    assert np.isclose(weights.sum(), area, rtol=1e-12)
    # coarser: split once (edges halved), then the split mesh's edge midpoints
    points, weights = fit_samples(vertices, faces, edge * 0.3)
    assert len(points) == 4 * 3 * len(faces) // 2
    assert np.isclose(weights.sum(), area, rtol=1e-12)
    # the points lie on the original facets: inside the sphere, never outside
    assert np.linalg.norm(points, axis=1).max() <= 10.0 + 1e-9


def test_edge_midpoint_rule_integrates_quadratics_over_the_facets_exactly():
    vertices, faces = _sphere()
    points, weights = edge_midpoints(vertices, faces)
    tri = vertices[faces]
    # exact integral of x^2 over each flat triangle: area / 6 * (sum of x_i^2 + sum_{i<j} x_i x_j)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    x = tri[:, :, 0]
    exact = np.sum(area / 6.0 * (np.sum(x**2, axis=1) + x[:, 0] * x[:, 1] + x[:, 1] * x[:, 2] + x[:, 2] * x[:, 0]))
    assert np.isclose(np.sum(weights * points[:, 0] ** 2), exact, rtol=1e-12)
    # the vertex rule does not: it puts all the weight on the corners
    assert not np.isclose(np.sum(vertex_areas(vertices, faces) * vertices[:, 0] ** 2), exact, rtol=1e-3)


def test_fit_sample_mesh_joins_the_points_by_triangles_facing_out():
    from bonecad.mesh.sampling import fit_sample_mesh

    vertices, faces = _sphere()
    edge = median_edge_mm(vertices, faces)
    for spacing in (edge * 1.01, edge * 0.6, edge * 0.3):
        points, weights, triangles = fit_sample_mesh(vertices, faces, spacing)
        assert np.array_equal(points, fit_samples(vertices, faces, spacing)[0])
        tri = points[triangles]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        assert (np.einsum("ij,ij->i", normal, tri.mean(axis=1)) > 0).all()  # outwards, as the mesh's faces
        assert np.array_equal(np.unique(triangles), np.arange(len(points)))  # every point in a triangle
