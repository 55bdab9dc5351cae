"""Signed deviation between the polygonal model and a CAD shape, both ways.

Sign convention (both directions): **positive = the mesh lies outside the CAD
model** there. Mesh -> CAD: signed distance of a mesh sample to the shape along
the shape's outward normal. CAD -> mesh: minus the signed distance of a CAD
sample to the mesh, so the two histograms read the same way.

Method and error bound
----------------------
1. The shape is tessellated finely (:func:`~bonecad.occ.tessellate.tessellate`,
   coverage checked against exact face areas) and each query point's nearest
   triangle is found exactly (:class:`~bonecad.mesh.closest.TriangleLocator`,
   a bounding-box tree).
2. On faces with a spline surface (all B-spline/Bezier faces, and analytic faces
   converted exactly), the point is projected onto the exact surface by
   Gauss-Newton from the (u, v) of that nearest point (``splines.project.project_faces``).
   The result is accepted when the foot point is a stationary point (tangential
   residual below ``residual_tol_mm``): the distance is then exact to rounding
   (1e-9 mm) for that foot point, and the foot point is the global nearest
   whenever the tessellation's chord error is far below the surface's radius of
   curvature (the start lies in the foot point's basin).
   A foot point stopped at its face's boundary is projected again on the face
   across it, from that face's tessellation node nearest to the stopped point
   (same acceptance test). CAD -> mesh samples are drawn on the exact surface
   directly (:func:`sample_shape`) and their distances to the mesh are exact.
3. Points still not accepted (foot point on a crease or outer boundary, failed
   conversion) keep the tessellation distance, whose error is at most the
   measured chord error of the face (``Tessellation.chord_error_mm``); the
   result reports the share refined and this bound
   (``DeviationResult.unrefined_bound_mm``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from collections.abc import Callable

import numpy as np

from bonecad.mesh.sampling import spatial_order, triangle_areas
from bonecad.mesh.closest import TriangleLocator
from bonecad.splines.project import project_faces
from bonecad.analysis.statistics import DeviationStats, Histogram, deviation_stats, histogram, share_within
from bonecad.mesh.tessellation import Tessellation

#: the anatomical regions a caller can label samples with
REGIONS = ("distal", "shaft", "proximal")

RegionSpec = Callable[[np.ndarray], np.ndarray] | None


@dataclass(frozen=True)
class SurfaceSamples:
    """Area-weighted random samples of a triangle surface.

    points : (N, 3) mm; triangle : (N,) index; barycentric : (N, 3);
    weights : (N,) mm^2 each sample stands for (total area / N each)
    """

    points: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray
    weights: np.ndarray


def sample_surface(vertices: np.ndarray, faces: np.ndarray, count: int, *, seed: int = 0,
                   areas: np.ndarray | None = None, order: np.ndarray | None = None) -> SurfaceSamples:
    """``count`` points distributed by area on a triangle mesh (deterministic for ``seed``), stratified: the
    mesh's area, its triangles taken in ``spatial_order``, is cut into ``count`` equal strata (compact
    patches) and one point drawn uniformly in each. Each point still lies anywhere with a density
    proportional to area, but a share of the surface (within a deviation, in a region) is estimated with
    less sampling noise than from independent draws: TLEM2's tibia, share within 0.1 mm of its NURBS model,
    100 k samples, 6 seeds: SD 0.048 against 0.125 percentage points.

    areas : the triangles' areas (mm^2); order : their ``spatial_order``; when the caller has them (None:
    computed here)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if count <= 0:
        raise ValueError(f"sample count must be > 0, got {count}")
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"need vertices (n, 3) and faces (m, 3), got {vertices.shape}, {faces.shape}")
    areas = triangle_areas(vertices, faces) if areas is None else areas
    order = spatial_order(vertices, faces) if order is None else order
    total = areas.sum()
    if not total > 0:
        raise ValueError("mesh has zero area")
    rng = np.random.default_rng(seed)
    cdf = np.cumsum(areas[order]) / total
    strata = (np.arange(count) + rng.random(count)) / count
    chosen = order[np.minimum(np.searchsorted(cdf, strata, side="right"), len(faces) - 1)]
    r1 = np.sqrt(rng.random(count))
    r2 = rng.random(count)
    bary = np.column_stack([1 - r1, r1 * (1 - r2), r1 * r2])
    points = np.einsum("nk,nkj->nj", bary, vertices[faces[chosen]])  # only the chosen triangles' corners
    return SurfaceSamples(points, chosen, bary, np.full(count, total / count))


@dataclass(frozen=True)
class DirectionResult:
    """Deviation of one direction (mesh -> CAD or CAD -> mesh).

    points : (N, 3) sample points, mm; deviation_mm : (N,) signed (see module doc)
    weights : (N,) mm^2; labels : (N,) region names ('' when no regions were given)
    refined : (N,) bool, mesh -> CAD: distance from exact projection (False: tessellation based);
        CAD -> mesh: the sample lies on the exact surface (:func:`sample_shape`)
    """

    points: np.ndarray
    deviation_mm: np.ndarray
    weights: np.ndarray
    labels: np.ndarray
    refined: np.ndarray
    stats: DeviationStats
    histogram: Histogram
    region_stats: dict[str, DeviationStats] = field(default_factory=dict)
    region_histograms: dict[str, Histogram] = field(default_factory=dict)

    def share_within(self, limit_mm: float) -> float:
        """Area share of the samples with |deviation| <= ``limit_mm`` (mm), exact (not band-resolved)."""
        return share_within(self.deviation_mm, self.weights, limit_mm)

    def to_dict(self) -> dict:
        return {
            "samples": int(len(self.deviation_mm)),
            "refined_share": float(self.refined.mean()) if len(self.refined) else 0.0,
            "stats": self.stats.to_dict(),
            "histogram": self.histogram.to_dict(),
            "regions": {
                name: {"stats": self.region_stats[name].to_dict(), "histogram": self.region_histograms[name].to_dict()}
                for name in self.region_stats
            },
        }


@dataclass(frozen=True)
class DeviationResult:
    """Both directions, with the accuracy of the method.

    unrefined_bound_mm : largest chord error of the tessellation's triangles
        within reach of the mesh -> CAD distances not refined on the exact
        surface (bounds the error of every such distance; 0.0 when all were refined)
    vertex_deviation_mm : (n,) signed deviation at each vertex of the mesh the colour
        map draws (``shape_deviation(map_vertices=...)``): its distance to the tessellation,
        within the tessellation's chord error (``[analysis] tessellation_deflection_mm``) of the exact one
    timings_s : seconds per step
    """

    mesh_to_cad: DirectionResult
    cad_to_mesh: DirectionResult
    unrefined_bound_mm: float
    vertex_deviation_mm: np.ndarray
    timings_s: dict[str, float]

    def to_dict(self) -> dict:
        return {
            "sign_convention": "positive = mesh outside the CAD model",
            "mesh_to_cad": self.mesh_to_cad.to_dict(),
            "cad_to_mesh": self.cad_to_mesh.to_dict(),
            "unrefined_bound_mm": self.unrefined_bound_mm,
            "timings_s": dict(self.timings_s),
        }


@dataclass(frozen=True)
class SignedDistance:
    """distance_mm : (N,) signed (positive outside); foot : (N, 3); refined : (N,) bool; face : (N,) int."""

    distance_mm: np.ndarray
    foot: np.ndarray
    refined: np.ndarray
    face: np.ndarray


def _signed(points, closest, normal):
    diff = points - closest
    dist = np.linalg.norm(diff, axis=1)
    sign = np.where(np.einsum("ij,ij->i", diff, normal) < 0, -1.0, 1.0)
    return sign * dist


def signed_distance_to_shape(
    points: np.ndarray,
    tess: Tessellation,
    *,
    locator: TriangleLocator | None = None,
    residual_tol_mm: float = 1e-6,
) -> SignedDistance:
    """Signed distances (mm, positive outside) of ``points`` (N, 3) to the tessellated shape.

    Exact projection on each face's spline surface where it converges, started
    from the nearest point of the tessellation (module doc).
    """
    points = np.asarray(points, dtype=np.float64)
    locator = locator or TriangleLocator(tess.vertices, tess.triangles)
    near = locator.query(points)
    dist = np.empty(len(points))
    foot = np.empty((len(points), 3))
    face = tess.triangle_face[near.triangle]
    refined = np.zeros(len(points), dtype=bool)
    tri = tess.triangles[near.triangle]
    uv_start = np.einsum("nk,nkj->nj", near.barycentric, tess.uv[tri])
    sset = tess.packed_surfaces
    sel = np.flatnonzero(sset.group[face] >= 0)
    if len(sel):
        proj = project_faces(sset, face[sel], points[sel], uv_start[sel])
        n = np.where(tess.reversed_faces[face[sel]][:, None], -proj.normal, proj.normal)
        exact = _signed(points[sel], proj.foot, n)
        ok = (proj.residual_mm <= residual_tol_mm) & np.isfinite(exact)
        dist[sel[ok]] = exact[ok]
        foot[sel[ok]] = proj.foot[ok]
        refined[sel[ok]] = True
    if len(sel) and tess.face_count > 1:
        # a foot point stopped at its face's boundary: the nearest point may lie on the
        # face across it; start again there, from that face's tessellation node nearest
        # to the stopped foot point (same acceptance test)
        stopped = ~refined[sel] & np.isfinite(proj.foot).all(axis=1)
        _retry_across(tess, points, sel[stopped], proj.foot[stopped], face, residual_tol_mm, dist, foot, refined)
    rest = np.flatnonzero(~refined)
    if len(rest):
        near = _subset(near, rest)
        dist[rest] = _tessellation_distance(points[rest], tess, near)
        foot[rest] = near.points
        face[rest] = tess.triangle_face[near.triangle]
    return SignedDistance(dist, foot, refined, face)


def _tessellation_distance(points: np.ndarray, tess: Tessellation, near) -> np.ndarray:
    """(N,) signed distance (mm) of points to their exact nearest points ``near`` on the tessellation,
    signed by the normal interpolated there (within the chord error of the exact surface's)."""
    normal = np.einsum("nk,nkj->nj", near.barycentric, tess.normals[tess.triangles[near.triangle]])
    return _signed(points, near.points, normal)


def sample_shape(tess: Tessellation, count: int, *, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``count`` area-weighted samples on the exact surface of a tessellated shape.

    A triangle is drawn by its flat area and a point in it by uniform barycentric
    weights; on a face with a spline surface the sample is S(u, v) at the
    interpolated parameters, exactly on the surface with no projection. Its
    density on the surface is then proportional to flat area / (uv area x
    |S_u x S_v|), so each sample is weighted by |S_u x S_v| x uv area / flat area
    (importance sampling: unbiased exact area per triangle). Weights are scaled
    to sum to the exact area of the shape. Returns points (count, 3), weights
    (count,) mm^2, and on_surface (count,) bool (False: a face without a spline
    surface, whose triangles are the geometry).
    """
    samples = sample_surface(tess.vertices, tess.triangles, count, seed=seed)
    points = samples.points.copy()
    weights = samples.weights.copy()
    on_surface = np.zeros(count, dtype=bool)
    face = tess.triangle_face[samples.triangle]
    sset = tess.packed_surfaces
    sel = np.flatnonzero(sset.group[face] >= 0)
    if len(sel):
        t = samples.triangle[sel]
        tri_uv = tess.uv[tess.triangles[t]]
        uv = np.einsum("nk,nkj->nj", samples.barycentric[sel], tri_uv)
        sample = sset.evaluate(face[sel], uv[:, 0], uv[:, 1], order=1)
        s, su, sv = sample.points, sample.du, sample.dv
        e1, e2 = tri_uv[:, 1] - tri_uv[:, 0], tri_uv[:, 2] - tri_uv[:, 0]
        uv_area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
        flat = tess.triangle_areas()[t]
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.linalg.norm(np.cross(su, sv), axis=1) * uv_area / flat
        ok = np.isfinite(ratio) & (flat > 0)
        points[sel[ok]] = s[ok]
        weights[sel[ok]] *= ratio[ok]
        on_surface[sel[ok]] = True
    weights *= tess.face_area_exact_mm2.sum() / weights.sum()
    return points, weights, on_surface


def _subset(near, rows: np.ndarray):
    return type(near)(near.points[rows], near.triangle[rows], near.barycentric[rows], near.distance[rows])


#: tessellation nodes searched about a stopped foot point for one on another face
_ACROSS_NODES = 16


def _retry_across(tess: Tessellation, points, rows, stopped_foot, face, residual_tol_mm, dist, foot, refined):
    """Project ``points[rows]`` onto the faces next to their stopped foot points; update in place."""
    from scipy.spatial import cKDTree

    if len(rows) == 0:
        return
    sset = tess.packed_surfaces
    k = min(_ACROSS_NODES, len(tess.vertices))
    _, nodes = cKDTree(tess.vertices).query(stopped_foot, k=k)
    nodes = nodes.reshape(len(rows), k)
    other = tess.node_face[nodes]
    usable = (other != face[rows][:, None]) & (sset.group[other] >= 0)
    has = usable.any(axis=1)
    rows, nodes, other, usable = rows[has], nodes[has], other[has], usable[has]
    if len(rows) == 0:
        return
    pick = nodes[np.arange(len(rows)), np.argmax(usable, axis=1)]
    target = tess.node_face[pick]
    proj = project_faces(sset, target, points[rows], tess.uv[pick])
    n = np.where(tess.reversed_faces[target][:, None], -proj.normal, proj.normal)
    exact = _signed(points[rows], proj.foot, n)
    ok = (proj.residual_mm <= residual_tol_mm) & np.isfinite(exact)
    dist[rows[ok]] = exact[ok]
    foot[rows[ok]] = proj.foot[ok]
    face[rows[ok]] = target[ok]
    refined[rows[ok]] = True


def _labels(points: np.ndarray, regions: RegionSpec) -> np.ndarray:
    if regions is None:
        return np.full(len(points), "", dtype=object)
    labels = np.asarray(regions(points), dtype=object)
    if labels.shape != (len(points),):
        raise ValueError(f"region function returned shape {labels.shape}, expected ({len(points)},)")
    unknown = set(labels.tolist()) - set(REGIONS)
    if unknown:
        raise ValueError(f"unknown region labels {sorted(unknown)}; expected {REGIONS}")
    return labels


def summarise(
    points: np.ndarray,
    deviation_mm: np.ndarray,
    weights: np.ndarray,
    labels: np.ndarray,
    refined: np.ndarray,
    edges_mm: np.ndarray,
) -> DirectionResult:
    """Statistics and histograms (band edges in mm) overall and per region label (labels '' mean none)."""
    edges = edges_mm
    region_stats, region_hists = {}, {}
    for name in REGIONS:
        sel = labels == name
        if sel.any():
            region_stats[name] = deviation_stats(deviation_mm[sel], weights[sel])
            region_hists[name] = histogram(deviation_mm[sel], weights[sel], edges)
    return DirectionResult(
        points=points,
        deviation_mm=deviation_mm,
        weights=weights,
        labels=labels,
        refined=refined,
        stats=deviation_stats(deviation_mm, weights),
        histogram=histogram(deviation_mm, weights, edges),
        region_stats=region_stats,
        region_histograms=region_hists,
    )


def shape_deviation(
    vertices: np.ndarray,
    faces: np.ndarray,
    tessellation: Tessellation,
    *,
    regions: RegionSpec = None,
    sample_points: int,
    edges_mm: np.ndarray,
    seed: int = 0,
    map_vertices: np.ndarray | None = None,
    mesh_locator: TriangleLocator | None = None,
) -> DeviationResult:
    """Deviation between a triangle mesh (``vertices`` (n, 3) mm, ``faces`` (m, 3)) and a CAD shape,
    given by its tessellation with exact surfaces (``bonecad.occ.tessellate``; a closed shell or
    solid, faces oriented outwards).

    Parameters
    ----------
    regions : function of (N, 3) points returning N labels from :data:`REGIONS`,
        applied to the samples of both directions; None for no regions
    sample_points : samples per direction (``[analysis] sample_points``)
    edges_mm : histogram band edges (``statistics.band_edges``)
    seed : seed of the area-weighted sampling (same seed, same samples)
    map_vertices : (k, 3) mm, the points of ``vertex_deviation_mm`` (the vertices of the mesh the colour
        map draws, e.g. a simplified copy of the same surface); None: ``vertices``
    mesh_locator : the closest-point tree of the mesh (with its vertex normals and triangle areas) when the
        caller has it (None: built here)
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    count = sample_points
    timings = {}
    tess = tessellation

    t0 = time.perf_counter()
    mesh_locator = mesh_locator or TriangleLocator(vertices, faces)
    samples = sample_surface(vertices, faces, count, seed=seed, areas=mesh_locator.triangle_areas,
                             order=mesh_locator.spatial_order)
    shape_locator = TriangleLocator(tess.vertices, tess.triangles)  # shared with the vertex distances
    sd = signed_distance_to_shape(samples.points, tess, locator=shape_locator)
    forward = summarise(
        samples.points, sd.distance_mm, samples.weights, _labels(samples.points, regions), sd.refined, edges_mm
    )
    timings["mesh_to_cad"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    cad_points, weights, on_surface = sample_shape(tess, count, seed=seed + 1)
    near = mesh_locator.query(cad_points)
    normal = np.einsum("nk,nkj->nj", near.barycentric, mesh_locator.vertex_normals[faces[near.triangle]])
    back_dev = -_signed(cad_points, near.points, normal)
    backward = summarise(cad_points, back_dev, weights, _labels(cad_points, regions), on_surface, edges_mm)
    timings["cad_to_mesh"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    # the colour map's: a picture, interpolated across the mesh's triangles
    shown = vertices if map_vertices is None else np.asarray(map_vertices, dtype=np.float64)
    vertex_deviation = _tessellation_distance(shown, tess, shape_locator.query(shown))
    timings["vertices"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    # the chord error bounds only the distances left on the tessellation: measured about them
    bound = tess.chord_error_near(samples.points[~sd.refined], sd.distance_mm[~sd.refined])
    timings["chord_error_bound"] = time.perf_counter() - t0
    return DeviationResult(
        mesh_to_cad=forward,
        cad_to_mesh=backward,
        unrefined_bound_mm=bound,
        vertex_deviation_mm=vertex_deviation,
        timings_s=timings,
    )
