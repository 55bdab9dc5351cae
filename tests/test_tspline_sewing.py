"""Whatever the fit refines, the T-spline sews into a valid closed solid.

A property test over random local refinements of the phantom's fitted tube:
clusters of elements anywhere, at the periodic seam (s = 0), at both apex
rings (the ring row and the apex rows, which end in T-points) and beside
T-junctions, halved in s, in t or both, over several rounds, with the control
points then moved at random (so the surface is not only the smooth phantom).
Each T-spline goes through the production conversion: apex caps built against
the refined tube, Bezier extraction, merging into one B-spline face per
tensor-product block, sewing into an outward solid, which must be valid
(BRepCheck), closed, one shell with every face, and enclose the volume the
T-spline patches enclose. Explicit examples keep the two failures it found:
a solid turned inside out, and a crumpled tube whose faces left 2 free edges.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import Phase, example, given, settings
from hypothesis import strategies as st

from bonecad.splines.tspline import TSpline, refine_elements
from bonecad.splines.tspline.tmesh import END_LINES
from bonecad.tspline_model.model import TSplineModel
from tests.defaults import SETTINGS

REGIONS = ("anywhere", "seam", "distal_ring", "proximal_ring", "t_junctions")
AXES = ("s", "t", "both", "alternate")
#: element rows from each end that count as the ring's: the ring row and the apex rows
RING_ROWS = 1 + SETTINGS.tspline.apex_rows


class Fitted:
    """A fitted T-spline model and the mesh points inside its two apex holes (bone coordinates, mm).

    Not a dataclass: Hypothesis prints a failing example's arguments, a dataclass field by field."""

    def __init__(self, model: TSplineModel, distal_points: np.ndarray, proximal_points: np.ndarray):
        self.model, self.distal_points, self.proximal_points = model, distal_points, proximal_points

    def __repr__(self) -> str:
        return f"Fitted(tube of {self.model.control_points} control points)"


@pytest.fixture(scope="module")
def phantom_fitted(phantom, phantom_frame, phantom_tspline_model) -> Fitted:
    """The phantom's fitted model and its apex-hole points."""
    from bonecad.tspline_model.model import fit_points, hole_masks

    model = phantom_tspline_model
    vertices, _ = fit_points(phantom, phantom_frame, SETTINGS.tspline)
    distal, proximal = hole_masks(vertices, model.frame, SETTINGS.curves.apex_hole_radius_mm)
    return Fitted(model, vertices[distal], vertices[proximal])


def candidates(ts: TSpline, region: str) -> np.ndarray:
    """Elements of one region of the tube, in index order."""
    ext = ts.extraction
    s_n, t_n = ts.mesh.shape
    i0, i1, j0, j1 = ext.index_bounds.T
    first, last = END_LINES - 1, t_n - END_LINES  # the ring t-lines (the clamped ends)
    mask = {
        "anywhere": np.ones(ext.n_elements, dtype=bool),
        "seam": (i0 == 0) | (i1 >= s_n),
        "distal_ring": j0 < first + RING_ROWS,
        "proximal_ring": j1 > last - RING_ROWS,
        # an element longer than one grid cell has a T-junction on its side
        "t_junctions": (i1 - i0 > 1) | (j1 - j0 > 1),
    }[region]
    return np.flatnonzero(mask)


def cluster(ts: TSpline, region: str, where: tuple[float, float], count: int) -> np.ndarray:
    """The ``count`` elements of a region nearest (in parameters, s wrapped) to the point ``where``
    (fractions of the s period and of the t range): repeated rounds at one point refine deeper there."""
    ext = ts.extraction
    pool = candidates(ts, region)
    if pool.size == 0:
        pool = np.arange(ext.n_elements)
    period = ts.mesh.s_period
    t_lo, t_hi = ts.mesh.t_range
    s = ext.s_bounds[pool].mean(axis=1)
    t = ext.t_bounds[pool].mean(axis=1)
    ds = np.abs(np.mod(s - where[0] * period + 0.5 * period, period) - 0.5 * period)
    return pool[np.argsort(ds + np.abs(t - (t_lo + where[1] * (t_hi - t_lo))), kind="stable")[:count]]


def split_axes(elements: np.ndarray, axes: str) -> np.ndarray:
    """(n, 2) bool [halve in s, halve in t] per element."""
    out = np.zeros((len(elements), 2), dtype=bool)
    if axes in ("s", "both"):
        out[:, 0] = True
    if axes in ("t", "both"):
        out[:, 1] = True
    if axes == "alternate":
        out[np.arange(len(elements)), elements % 2] = True
    return out


def refined(tube: TSpline, spots, rounds, noise_mm: float, seed: int) -> TSpline:
    """The tube refined round by round (region, index into ``spots``, element count, split axes),
    its control points then moved by N(0, noise_mm) (mm)."""
    for region, spot, count, axes in rounds:
        elements = cluster(tube, region, spots[spot], count)
        tube = refine_elements(tube, elements, split_axes(elements, axes)).tspline
    move = np.random.default_rng(seed).normal(0.0, noise_mm, tube.control_points.shape)
    return tube.with_control_points(tube.control_points + move, tube.weights)


def enclosed_volume_mm3(patches: list[TSpline]) -> float:
    """Volume the patches enclose (a closed, consistently oriented surface; mm^3): the divergence
    theorem, V = 1/3 sum of integrals of (P - c) . (P_s x P_t), 5-point Gauss per element and
    direction (exact on bicubic polynomial patches, whose integrand is of degree 8)."""
    g, gw = np.polynomial.legendre.leggauss(5)
    g, gw = 0.5 * (g + 1.0), 0.5 * gw
    centre = patches[0].control_points.mean(axis=0)
    total = 0.0
    for ts in patches:
        ext = ts.extraction
        hs, ht = np.diff(ext.s_bounds, axis=1)[:, 0], np.diff(ext.t_bounds, axis=1)[:, 0]
        s = (ext.s_bounds[:, :1, None] + g[None, :, None] * hs[:, None, None] + 0.0 * g[None, None, :]).ravel()
        t = (ext.t_bounds[:, :1, None] + 0.0 * g[None, :, None] + g[None, None, :] * ht[:, None, None]).ravel()
        d = ts.evaluate(s, t, order=1)
        flux = np.einsum("ij,ij->i", d.points - centre, np.cross(d.du, d.dv)).reshape(-1, 5, 5)
        total += float(np.einsum("eij,i,j,e->", flux, gw, gw, hs * ht))
    return abs(total) / 3.0


#: places that rounds refine (fractions of the s period and of the t range); rounds that share one
#: refine deeper there
spot_strategy = st.tuples(st.floats(0.0, 1.0), st.floats(0.0, 1.0))
round_strategy = st.tuples(st.sampled_from(REGIONS), st.integers(0, 2), st.integers(1, 30), st.sampled_from(AXES))


# derandomized: the same examples on every run; no shrinking, which took over 5 minutes on a failure
# (a failing example prints as generated; rerun it with shrinking to simplify it)
@settings(max_examples=30, deadline=None, derandomize=True, phases=(Phase.explicit, Phase.generate))
@given(spots=st.lists(spot_strategy, min_size=3, max_size=3), rounds=st.lists(round_strategy, min_size=1, max_size=8),
       noise_mm=st.sampled_from([0.0, 0.05, 0.3, 0.5]), seed=st.integers(0, 2**16))
@example(spots=[(0.0, 0.5)] * 3, rounds=[("seam", 0, 30, "both")] * 4, noise_mm=0.3, seed=1)
@example(spots=[(0.0, 0.0), (0.5, 1.0), (0.3, 0.0)], rounds=[("distal_ring", 0, 30, "s"), ("proximal_ring", 1, 30, "s"),
         ("distal_ring", 2, 20, "both"), ("proximal_ring", 1, 20, "both")], noise_mm=0.3, seed=2)
@example(spots=[(0.5, 0.5)] * 3, rounds=[("t_junctions", 0, 10, "alternate")] * 5, noise_mm=0.05, seed=3)
# crumpled: elements of 0.1 mm moved 0.5 mm; a merged face's side curls back within 10 um of itself, which
# sewing left unsewn (2 free edges) until the faces were bounded by one edge per element side
@example(spots=[(0.2830830576678356, 0.0)] * 3, rounds=[("t_junctions", 0, n, axes) for n, axes in (
    (11, "both"), (26, "s"), (28, "alternate"), (11, "alternate"), (28, "t"), (14, "s"), (19, "t"), (9, "t"),
    (26, "both"))], noise_mm=0.5, seed=1465)
# OpenCascade's ray classification called the point at infinity inside this solid, which came out inside out
@example(spots=[(0.0, 0.3340462118042096), (0.9799111049912494, 0.035344995795660646),
                (0.9799111049912494, 0.23846930323429288)],
         rounds=[("seam", 0, 1, "both"), ("distal_ring", 0, 9, "t"), ("t_junctions", 0, 20, "both"),
                 ("distal_ring", 1, 22, "t"), ("distal_ring", 0, 26, "alternate"), ("distal_ring", 2, 16, "alternate"),
                 ("distal_ring", 0, 9, "t"), ("seam", 0, 2, "alternate")], noise_mm=0.5, seed=4861)
def test_refined_tube_sews_into_a_valid_closed_solid(phantom_fitted, spots, rounds, noise_mm, seed):
    from OCP.TopAbs import TopAbs_SHELL, TopAbs_SOLID
    from OCP.TopExp import TopExp_Explorer

    from bonecad.occ.brep import faces, free_edge_count, is_valid, volume_mm3
    from bonecad.occ.tspline import tensor_product_blocks
    from bonecad.splines.tspline.tensor import panel_plan
    from bonecad.tspline_model.model import apex_caps, occ_shape

    model = phantom_fitted.model
    tube = refined(model.tspline, spots, rounds, noise_mm, seed)
    caps = apex_caps(tube, model.parameterisation, phantom_fitted.distal_points, phantom_fitted.proximal_points)
    solid, face_names = occ_shape(tube, caps, model.parameterisation, model.frame, settings=SETTINGS.tspline)

    assert solid.ShapeType() == TopAbs_SOLID and is_valid(solid)
    shells, explorer = 0, TopExp_Explorer(solid, TopAbs_SHELL)
    while explorer.More():
        shells += 1
        explorer.Next()
    assert shells == 1
    assert free_edge_count(solid) == 0
    patches = [tube, *(c.tspline for c in caps)]
    par, st = model.parameterisation, SETTINGS.tspline
    assert st.face_layout == "panels"  # the shipped layout: the tube's panels, the caps' blocks
    tube_faces = len(panel_plan(tube, t_cuts=(par.t_distal, par.t_proximal), face_cost=st.panel_face_cost,
                                t_step=st.panel_t_step))
    assert len(faces(solid)) == len(face_names) == tube_faces + sum(len(tensor_product_blocks(c.tspline))
                                                                    for c in caps)
    # the solid encloses what the T-spline surfaces enclose (all faces there, all facing out)
    volume = volume_mm3(solid, 1e-9)  # at the default 1e-6 it was up to 2.6e-6 off, at 1e-8 2.4e-7
    assert volume > 0
    assert volume == pytest.approx(enclosed_volume_mm3(patches), rel=1e-7)
