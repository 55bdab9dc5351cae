"""tspline.iga read by a reader written here from the format (not the writer's code): the surface, the
partition of unity, area and volume against OpenCascade's (the phantom's T-spline model; about 30 s with
the model's fit)."""
from __future__ import annotations

from dataclasses import dataclass
from math import comb
from pathlib import Path

import numpy as np
import pytest

from bonecad.export.registry import export
from bonecad.tspline_model.model import to_scanner


@dataclass
class IgaFile:
    kind: str
    nodes: np.ndarray  # (n, 3)
    weights: np.ndarray  # (n,)
    elements: list[tuple[np.ndarray, np.ndarray]]  # (global indices (k,), rows (k, 16))
    sets: dict[str, tuple[str, list]]


def read_iga(path: Path) -> IgaFile:
    """The Rhino T-Splines .iga format: type, nodeN, elemN, node x y z w, belem k p q + k indices + k rows
    of (p+1)(q+1) Bernstein coefficients (s fastest), set n kind name entries."""
    tokens = [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    kind, nodes, weights, elements, sets = "", [], [], [], {}
    i = 0
    n_nodes = n_elems = -1
    while i < len(tokens):
        t = tokens[i]
        if t[0] == "type":
            kind = t[1]
        elif t[0] == "nodeN":
            n_nodes = int(t[1])
        elif t[0] == "elemN":
            n_elems = int(t[1])
        elif t[0] == "node":
            x, y, z, w = map(float, t[1:5])
            nodes.append((x, y, z))
            weights.append(w)
        elif t[0] == "belem":
            k, p, q = map(int, t[1:4])
            idx = np.array(tokens[i + 1], dtype=np.int64)
            rows = np.array(tokens[i + 2:i + 2 + k], dtype=np.float64)
            assert len(idx) == k and rows.shape == (k, (p + 1) * (q + 1))
            elements.append((idx, rows))
            i += 1 + k
        elif t[0] == "set":
            n, set_kind, name = int(t[1]), t[2], t[3]
            rest = t[4:]
            entries = list(zip(map(int, rest[::2]), rest[1::2])) if set_kind == "side" else list(map(int, rest))
            assert len(entries) == n
            sets[name] = (set_kind, entries)
        i += 1
    assert len(nodes) == n_nodes and len(elements) == n_elems
    return IgaFile(kind, np.array(nodes), np.array(weights), elements, sets)


def _bernstein(x: np.ndarray, d: int = 0) -> np.ndarray:
    """(n, 4) cubic Bernstein polynomials (or their first derivative) at x in [0, 1]."""
    if d == 0:
        return np.stack([comb(3, i) * x ** i * (1 - x) ** (3 - i) for i in range(4)], axis=1)
    b2 = np.stack([comb(2, i) * x ** i * (1 - x) ** (2 - i) for i in range(3)], axis=1)
    z = np.zeros((len(x), 1))
    return 3.0 * (np.hstack([z, b2]) - np.hstack([b2, z]))


def evaluate(f: IgaFile, e: int, u: np.ndarray, v: np.ndarray, derivatives: bool = False):
    """Points (n, 3) of element e at (u, v), and with ``derivatives`` also d/du, d/dv."""
    idx, rows = f.elements[e]
    wp = np.hstack([f.nodes[idx] * f.weights[idx, None], f.weights[idx, None]])  # (k, 4) homogeneous

    def hom(bu, bv):
        b = (bv[:, :, None] * bu[:, None, :]).reshape(len(u), 16)  # index 4 j + i: s fastest
        return b @ rows.T @ wp

    h = hom(_bernstein(u), _bernstein(v))
    x = h[:, :3] / h[:, 3:]
    if not derivatives:
        return x
    hu, hv = hom(_bernstein(u, 1), _bernstein(v)), hom(_bernstein(u), _bernstein(v, 1))
    xu = (hu[:, :3] - x * hu[:, 3:]) / h[:, 3:]
    xv = (hv[:, :3] - x * hv[:, 3:]) / h[:, 3:]
    return x, xu, xv


@pytest.fixture(scope="module")
def iga(phantom_tspline_model, tmp_path_factory):
    out = tmp_path_factory.mktemp("iga")
    path = export("tspline", phantom_tspline_model, out, only=["iga"])["iga"]
    return read_iga(path)


@pytest.mark.slow
def test_surface_within_1e9_mm_at_10000_points(iga, phantom_tspline_model):
    model = phantom_tspline_model
    patches = [to_scanner(model.tspline, model.frame)] + [to_scanner(c.tspline, model.frame) for c in model.caps]
    assert iga.kind == "surface"
    rng = np.random.default_rng(1)
    first = 0
    worst = 0.0
    count = 0
    for patch in patches:
        ext = patch.extraction
        elems = rng.integers(0, ext.n_elements, 10000 * ext.n_elements // len(iga.elements) + 1)
        u, v = rng.random(len(elems)), rng.random(len(elems))
        s = ext.s_bounds[elems, 0] + u * (ext.s_bounds[elems, 1] - ext.s_bounds[elems, 0])
        t = ext.t_bounds[elems, 0] + v * (ext.t_bounds[elems, 1] - ext.t_bounds[elems, 0])
        s = np.mod(s - patch.mesh.s_range[0], patch.mesh.s_period) + patch.mesh.s_range[0]
        expected = patch.evaluate(s, t).points
        for e in np.unique(elems):
            sel = elems == e
            got = evaluate(iga, first + e, u[sel], v[sel])
            worst = max(worst, float(np.max(np.linalg.norm(got - expected[sel], axis=1))))
        count += len(elems)
        first += ext.n_elements
    assert first == len(iga.elements) and count >= 10000
    assert worst < 1e-9


@pytest.mark.slow
def test_extraction_rows_are_a_partition_of_unity(iga):
    for idx, rows in iga.elements:
        assert np.allclose(rows.sum(axis=0), 1.0, atol=1e-12)
        assert len(np.unique(idx)) == len(idx)


@pytest.mark.slow
def test_sets_and_the_pole_functions(iga):
    kinds = {name: kind for name, (kind, _) in iga.sets.items()}
    assert kinds == {"distal_ring": "side", "proximal_ring": "side", "tube": "elem", "distal_cap": "elem",
                     "proximal_cap": "elem", "distal_pole": "node", "proximal_pole": "node"}
    assert {side for _, side in iga.sets["distal_ring"][1]} == {"BOTTOM"}
    # the pole is one function: on each cap element it is the only one non-zero at the pole (value 1 there)
    for end in ("distal", "proximal"):
        pole = iga.sets[f"{end}_pole"][1][0]
        for e in iga.sets[f"{end}_cap"][1]:
            assert pole in iga.elements[e][0]


@pytest.mark.slow
def test_area_and_volume_by_gauss_quadrature_match_opencascade(iga, phantom_tspline_model):
    from bonecad.occ.brep import area_mm2, volume_mm3

    g, w = np.polynomial.legendre.leggauss(16)
    g, w = 0.5 * (g + 1.0), 0.5 * w
    u, v = np.meshgrid(g, g, indexing="ij")
    ww = np.outer(w, w).ravel()
    area = volume = 0.0
    for e in range(len(iga.elements)):
        x, xu, xv = evaluate(iga, e, u.ravel(), v.ravel(), derivatives=True)
        n = np.cross(xu, xv)
        area += float(ww @ np.linalg.norm(n, axis=1))
        volume += float(ww @ np.einsum("ij,ij->i", x, n)) / 3.0
    shape = phantom_tspline_model.shape
    assert area == pytest.approx(area_mm2(shape, 1e-9), rel=1e-6)
    assert abs(volume) == pytest.approx(volume_mm3(shape, 1e-9), rel=1e-6)


def _sphere_surface(radius: float, hole_deg: float = 12.0):
    """A sphere as a periodic tube (least-squares fit) closed by two apex caps, as the bone's model is."""
    from bonecad.splines.tspline import TSpline
    from bonecad.splines.tspline.iga import closed_surface
    from bonecad.tspline_model.caps import build_cap

    period = 2 * np.pi * radius
    theta0 = np.radians(hole_deg)
    s_knots = np.linspace(0.0, period, 17)[:-1]
    t_knots = np.linspace(theta0, np.pi - theta0, 11)
    grid = TSpline.from_grid(s_knots, t_knots, np.zeros((16, 13, 3)), s_period=period)
    s, t = np.meshgrid(np.linspace(0, period, 120, endpoint=False), np.linspace(theta0, np.pi - theta0, 80))
    s, t = s.ravel(), t.ravel()

    def sphere(s, t):
        phi = 2 * np.pi * s / period
        return radius * np.stack([np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi), np.cos(t)], axis=1)

    a = grid.basis_matrix(s, t).toarray()
    cp, *_ = np.linalg.lstsq(a, sphere(s, t), rcond=None)
    tube = grid.with_control_points(cp)
    rng = np.random.default_rng(0)
    caps = []
    for end, z in (("distal", 1.0), ("proximal", -1.0)):
        th = rng.uniform(0, theta0 * 0.95, 200)
        th = th if z > 0 else np.pi - th
        hole = sphere(rng.uniform(0, period, 200), th)
        caps.append((end, build_cap(tube, end, hole, np.array([0.0, 0.0, z])).tspline))
    return closed_surface(tube, caps)


def test_laplace_beltrami_eigenvalues_of_a_sphere_from_the_files_basis(tmp_path):
    """The file's basis (tube C2, caps with one pole function each, C0 rings) on a sphere of radius 20 mm:
    the first eigenvalues of the Laplace-Beltrami operator are l (l + 1) / R^2 (l = 1: three, l = 2: five)."""
    import scipy.linalg

    from bonecad.splines.tspline.iga import iga_text

    radius = 20.0
    path = tmp_path / "sphere.iga"
    path.write_text(iga_text(_sphere_surface(radius)))
    f = read_iga(path)
    assert np.all(f.weights == 1.0)
    n = len(f.nodes)
    g, w = np.polynomial.legendre.leggauss(6)
    g, w = 0.5 * (g + 1.0), 0.5 * w
    u, v = (x.ravel() for x in np.meshgrid(g, g, indexing="ij"))
    ww = np.outer(w, w).ravel()
    bu, bv, du, dv = _bernstein(u), _bernstein(v), _bernstein(u, 1), _bernstein(v, 1)

    def tensor(a, b):
        return (b[:, :, None] * a[:, None, :]).reshape(len(u), 16)  # 4 j + i

    stiff, mass = np.zeros((n, n)), np.zeros((n, n))
    for idx, rows in f.elements:
        nb, nu_, nv = tensor(bu, bv) @ rows.T, tensor(du, bv) @ rows.T, tensor(bu, dv) @ rows.T  # (q, k)
        p = f.nodes[idx]
        xu, xv = nu_ @ p, nv @ p
        g11, g12, g22 = (np.einsum("ij,ij->i", a, b) for a, b in ((xu, xu), (xu, xv), (xv, xv)))
        det = g11 * g22 - g12 ** 2
        da = ww * np.sqrt(det)
        i11, i12, i22 = g22 / det, -g12 / det, g11 / det
        k = (np.einsum("q,qa,qb->ab", da * i11, nu_, nu_) + np.einsum("q,qa,qb->ab", da * i12, nu_, nv)
             + np.einsum("q,qa,qb->ab", da * i12, nv, nu_) + np.einsum("q,qa,qb->ab", da * i22, nv, nv))
        stiff[np.ix_(idx, idx)] += k
        mass[np.ix_(idx, idx)] += np.einsum("q,qa,qb->ab", da, nb, nb)
    values = scipy.linalg.eigh(stiff, mass, eigvals_only=True, subset_by_index=[0, 8])
    expected = np.array([0.0] + [2.0] * 3 + [6.0] * 5) / radius ** 2
    assert abs(values[0]) < 1e-8
    assert np.all(np.abs(values[1:] / expected[1:] - 1.0) < 0.005), values * radius ** 2
