"""Fit samples of a mesh: midpoint subdivision keeps the surface and carries per-vertex figures over."""
import numpy as np
import trimesh

from bonecad.mesh.sampling import fit_samples, median_edge_mm, midpoint_subdivision, vertex_areas


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


def test_fit_samples_split_a_coarse_mesh_until_its_edges_are_short_and_leave_a_fine_one_alone():
    vertices, faces = _sphere()
    coarse = median_edge_mm(vertices, faces)
    points, weights = fit_samples(vertices, faces, coarse / 3.0)
    assert len(points) > 10 * len(vertices)  # two rounds of splitting
    assert median_edge_mm(*midpoint_subdivision(*midpoint_subdivision(vertices, faces))) <= coarse / 3.0
    assert np.array_equal(points[: len(vertices)], vertices)
    assert np.isclose(weights.sum(), vertex_areas(vertices, faces).sum(), rtol=1e-12)
    # the new points lie on the original facets: at the sphere's radius or inside it, never outside
    assert np.linalg.norm(points, axis=1).max() <= 10.0 + 1e-9
    same, same_weights = fit_samples(vertices, faces, coarse * 1.01)
    assert np.array_equal(same, vertices) and np.allclose(same_weights, vertex_areas(vertices, faces))
