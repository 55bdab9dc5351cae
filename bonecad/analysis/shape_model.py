"""Statistical shape model of template control points (issue 21).

Each bone is the (n, 3) array of its template control points
(:mod:`bonecad.tspline_model.template`) in bone coordinates, which the
anatomical frame already aligns (origin at the plafond centre, axes lateral,
anterior, proximal; a left tibia mirrored to a right one). Optionally a
generalised Procrustes alignment (rigid, or similarity with scale) is laid
over it. The model: the mean, the principal modes (SVD of the centred
shapes), their variances (mm^2 summed over the control points), and the
bones' mode weights. A linear regression (ridge) from named parameters
(any table of per-bone measurements: the phantom's design parameters,
``bonecad measure``'s figures) to the mode weights turns a few
measurements into a tibia (``morph_weights``).

Figures (all in mm):

- compactness: cumulative share of the variance per number of modes;
- generalisation: leave-one-out; each bone rebuilt from a model of the
  others with k modes (its centred shape projected on them), measured as the
  area-weighted RMS distance from its mesh's points to the rebuilt surface;
- specificity: random shapes (mode weights ~ N(0, sd^2)), each at its RMS
  distance to the nearest training shape (corresponding surface points on a
  fixed (s, t) grid of the template).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from bonecad.errors import InputError
from bonecad.settings import ShapeModelSettings, TemplateSettings
from bonecad.splines.tspline.fit import initial_parameters, project_points
from bonecad.tspline_model.template import template_tspline

#: Format version of a saved shape model.
VERSION = 1


@dataclass(frozen=True)
class ShapeModel:
    """A shape model of template control points (mm).

    mean : (n, 3); modes : (k, 3 n) orthonormal rows; variances : (k,) mm^2 (sum over the control points);
    bones : the training bones' names; weights : (m, k) their mode weights (mm); parameter_names and
    parameters : (m, p) the training table (NaN where a bone lacks a value); alignment : as the settings.
    """

    mean: np.ndarray
    modes: np.ndarray
    variances: np.ndarray
    bones: tuple[str, ...]
    weights: np.ndarray
    parameter_names: tuple[str, ...]
    parameters: np.ndarray
    alignment: str

    @property
    def sd(self) -> np.ndarray:
        """(k,) standard deviation of each mode's weight (mm)."""
        return np.sqrt(self.variances)

    def compactness(self) -> np.ndarray:
        """(k,) cumulative share of the total variance held by the first 1..k modes."""
        total = self.variances.sum()
        return np.cumsum(self.variances) / total if total > 0 else np.ones(len(self.variances))

    def shape(self, weights: np.ndarray) -> np.ndarray:
        """(n, 3) control points of the shape with the given weights of the first len(weights) modes (mm)."""
        w = np.asarray(weights, dtype=np.float64)
        if w.ndim != 1 or len(w) > len(self.variances):
            raise InputError(f"the model has {len(self.variances)} modes; got {len(w)} mode weights")
        return self.mean + (w @ self.modes[: len(w)]).reshape(-1, 3)

    def parameter_range(self, name: str) -> tuple[float, float]:
        column = self.parameters[:, self.parameter_names.index(name)]
        return float(np.nanmin(column)), float(np.nanmax(column))

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """(arrays for an .npz, the JSON sidecar: version, names, alignment, compactness)."""
        arrays = {"mean": self.mean, "modes": self.modes, "variances": self.variances, "weights": self.weights,
                  "parameters": self.parameters}
        meta = {"version": VERSION, "bones": list(self.bones), "parameter_names": list(self.parameter_names),
                "alignment": self.alignment, "control_points": len(self.mean), "modes": len(self.variances),
                "sd_mm": np.round(self.sd, 4).tolist(), "compactness": np.round(self.compactness(), 5).tolist(),
                "parameter_ranges": {n: list(self.parameter_range(n)) for n in self.parameter_names}}
        return arrays, meta

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray], meta: Mapping) -> ShapeModel:
        if meta.get("version") != VERSION:
            raise InputError(f"shape model version {meta.get('version')!r}; this bonecad reads version {VERSION}")
        return cls(np.asarray(arrays["mean"]), np.asarray(arrays["modes"]), np.asarray(arrays["variances"]),
                   tuple(meta["bones"]), np.asarray(arrays["weights"]), tuple(meta["parameter_names"]),
                   np.asarray(arrays["parameters"], dtype=np.float64).reshape(len(meta["bones"]), -1),
                   str(meta["alignment"]))


# ------------------------------------------------------------------ alignment
def _fit_transform(source: np.ndarray, target: np.ndarray, scale: bool) -> np.ndarray:
    """``source`` moved onto ``target`` by the least-squares rotation, translation (and scale): Umeyama 1991."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    a, b = source - mu_s, target - mu_t
    u, sig, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(u @ vt))
    fix = np.diag([1.0, 1.0, d])
    rot = u @ fix @ vt
    factor = float((sig * np.diag(fix)).sum() / np.sum(a**2)) if scale else 1.0
    return factor * a @ rot + mu_t


def align(shapes: np.ndarray, alignment: str, *, iterations: int = 10) -> np.ndarray:
    """(m, n, 3) shapes aligned: "none" as given (bone coordinates), "rigid" / "similarity" by generalised
    Procrustes onto their mean (which keeps the first shape's place and, with scale, its centroid size)."""
    shapes = np.asarray(shapes, dtype=np.float64)
    if alignment == "none":
        return shapes
    if alignment not in ("rigid", "similarity"):
        raise ValueError(f"alignment must be none, rigid or similarity, got {alignment!r}")
    scale = alignment == "similarity"
    out = shapes.copy()
    ref = shapes[0]
    for _ in range(iterations):
        out = np.stack([_fit_transform(s, ref, scale) for s in out])
        new = _fit_transform(out.mean(axis=0), shapes[0], scale)
        if np.sqrt(np.mean((new - ref) ** 2)) < 1e-6:
            break
        ref = new
    return out


# ---------------------------------------------------------------------- model
def build_shape_model(shapes: np.ndarray, bones: Sequence[str], parameters: Mapping[str, np.ndarray],
                      settings: ShapeModelSettings) -> ShapeModel:
    """The shape model of (m, n, 3) template control points (mm) of ``bones``, with their named parameters
    (name -> m values; NaN where missing)."""
    shapes = np.asarray(shapes, dtype=np.float64)
    m = len(shapes)
    if m < 3 or shapes.ndim != 3 or shapes.shape[2] != 3:
        raise InputError(f"a shape model needs at least 3 bones' (n, 3) control points; got shape {shapes.shape}")
    if len(bones) != m:
        raise InputError(f"{m} shapes but {len(bones)} bone names")
    aligned = align(shapes, settings.alignment)
    mean = aligned.mean(axis=0)
    centred = (aligned - mean).reshape(m, -1)
    u, sig, vt = np.linalg.svd(centred, full_matrices=False)
    k = max(1, min(m - 1, int(np.sum(sig > 1e-9 * max(sig[0], 1e-300)))))
    modes = vt[:k]
    names = tuple(parameters)
    table = np.array([np.asarray(parameters[n], dtype=np.float64) for n in names]).T.reshape(m, len(names))
    return ShapeModel(mean, modes, sig[:k] ** 2 / (m - 1), tuple(bones), centred @ modes.T, names, table,
                      settings.alignment)


def morph_weights(model: ShapeModel, values: Mapping[str, float], settings: ShapeModelSettings) -> np.ndarray:
    """(k,) mode weights predicted from named parameter values (any subset of the model's parameters).

    A ridge regression of the weights on the given parameters (standardised over the training bones that
    have them all), fitted for that subset. Raises InputError naming the parameter when it is unknown or
    outside its training range widened by ``settings.range_margin`` of the range on each side.
    """
    if not values:
        raise InputError("give at least one parameter to morph from")
    for name, value in values.items():
        if name not in model.parameter_names:
            raise InputError(f"unknown parameter '{name}'; the model knows {', '.join(model.parameter_names)}")
        lo, hi = model.parameter_range(name)
        pad = settings.range_margin * (hi - lo)
        if not (lo - pad <= value <= hi + pad):
            raise InputError(f"parameter '{name}' = {value:g} is outside the model's range {lo - pad:g} to "
                             f"{hi + pad:g} (training {lo:g} to {hi:g}, margin {settings.range_margin:g} of the range)")
    cols = [model.parameter_names.index(n) for n in values]
    x = model.parameters[:, cols]
    rows = np.all(np.isfinite(x), axis=1)
    if rows.sum() < 2:
        raise InputError(f"fewer than 2 training bones have all of {', '.join(values)}")
    x, y = x[rows], model.weights[rows]
    mu, sd = x.mean(axis=0), x.std(axis=0)
    sd = np.where(sd > 0, sd, 1.0)
    z = (x - mu) / sd
    gram = z.T @ z
    ridge = settings.ridge * max(np.trace(gram), 1e-12) * np.eye(len(cols))
    coef = np.linalg.solve(gram + ridge, z.T @ (y - y.mean(axis=0)))
    query = (np.array([values[n] for n in values], dtype=np.float64) - mu) / sd
    return y.mean(axis=0) + query @ coef


def predict_parameters(model: ShapeModel, weights: np.ndarray, settings: ShapeModelSettings) -> dict[str, float]:
    """Each named parameter predicted from mode weights (the inverse regression: ridge of the parameter on the
    training bones' weights of the same modes), for a morph's record."""
    w = np.asarray(weights, dtype=np.float64)
    x = model.weights[:, : len(w)] / model.sd[: len(w)]
    out = {}
    for c, name in enumerate(model.parameter_names):
        y = model.parameters[:, c]
        rows = np.isfinite(y)
        if rows.sum() < 2:
            continue
        gram = x[rows].T @ x[rows]
        coef = np.linalg.solve(gram + settings.ridge * max(np.trace(gram), 1e-12) * np.eye(len(w)),
                               x[rows].T @ (y[rows] - y[rows].mean()))
        out[name] = float(y[rows].mean() + (w / model.sd[: len(w)]) @ coef)
    return out


# ------------------------------------------------------------------- figures
def surface_distance_mm(control_points: np.ndarray, template: TemplateSettings, points: np.ndarray,
                        weights: np.ndarray, start: tuple[np.ndarray, np.ndarray] | None = None) -> float:
    """Area-weighted RMS distance (mm) of points (a mesh's, bone coordinates) from the template surface with
    these control points. start : the points' (s, t) on a nearby template surface (their own fit), else
    found on a grid of this one."""
    ts = template_tspline(control_points, template)
    if start is None:
        _, _, d = initial_parameters(ts, points)
    else:
        _, _, d = project_points(ts, points, *start)
    return float(np.sqrt(np.sum(weights * d**2) / weights.sum()))


@dataclass(frozen=True)
class Held:
    """One bone's surface for the leave-one-out figures: its mesh points and weights (bone coordinates,
    mm, mm^2) and their (s, t) on its own template fit (the projection's start)."""

    points: np.ndarray
    weights: np.ndarray
    s: np.ndarray
    t: np.ndarray


def held_surface(control_points: np.ndarray, template: TemplateSettings, points: np.ndarray,
                 weights: np.ndarray, *, samples: int, seed: int) -> Held:
    """A bone's :class:`Held` surface from its template control points and its mesh points (mm) with their
    area weights (mm^2): at most ``samples`` of them, drawn by weight (seeded), each then weighing the same,
    so the RMS over them estimates the area-weighted RMS at a fraction of the projections."""
    if len(points) > samples:
        pick = np.sort(np.random.default_rng(seed).choice(len(points), size=samples, p=weights / weights.sum()))
        points, weights = points[pick], np.ones(samples)
    s, t, _ = initial_parameters(template_tspline(control_points, template), points)
    return Held(points, weights, s, t)


def generalisation_mm(shapes: np.ndarray, held: Sequence[Held], modes: Sequence[int], settings: ShapeModelSettings,
                      template: TemplateSettings) -> np.ndarray:
    """(m, len(modes)) leave-one-out generalisation: bone j rebuilt from the model of the others with k modes
    (its aligned centred shape projected on them), at its RMS distance from its own mesh points (mm)."""
    shapes = np.asarray(shapes, dtype=np.float64)
    m = len(shapes)
    out = np.empty((m, len(modes)))
    for j in range(m):
        others = np.delete(np.arange(m), j)
        model = build_shape_model(shapes[others], [str(i) for i in others], {}, settings)
        # the held-out bone in the model's alignment (none: as given)
        own = shapes[j] if model.alignment == "none" else _fit_transform(shapes[j], model.mean,
                                                                         model.alignment == "similarity")
        w_all = (own - model.mean).reshape(-1) @ model.modes.T
        for c, k in enumerate(modes):
            rebuilt = model.shape(w_all[: min(k, len(w_all))])
            if model.alignment != "none":  # back where the mesh is
                rebuilt = _fit_transform(rebuilt, shapes[j], model.alignment == "similarity")
            out[j, c] = surface_distance_mm(rebuilt, template, held[j].points, held[j].weights,
                                            (held[j].s, held[j].t))
    return out


def baselines_mm(shapes: np.ndarray, lengths: np.ndarray, held: Sequence[Held],
                 template: TemplateSettings) -> np.ndarray:
    """(m, 2) leave-one-out baselines: the mean shape of the others, and that mean scaled along and about the
    axis by the bone's length over the others' mean length (about the plafond centre, the origin), each at its
    RMS distance from the held-out bone's mesh points (mm)."""
    shapes = np.asarray(shapes, dtype=np.float64)
    out = np.empty((len(shapes), 2))
    for j in range(len(shapes)):
        others = np.delete(np.arange(len(shapes)), j)
        mean = shapes[others].mean(axis=0)
        factor = lengths[j] / lengths[others].mean()
        for c, cp in enumerate((mean, mean * factor)):
            out[j, c] = surface_distance_mm(cp, template, held[j].points, held[j].weights, (held[j].s, held[j].t))
    return out


def grid_points(control_points: np.ndarray, template: TemplateSettings, *, ns: int = 48, nt: int = 120) -> np.ndarray:
    """(ns nt, 3) points of the template surface on a fixed (s, t) grid (corresponding points on every shape)."""
    ts = template_tspline(control_points, template)
    (s0, _), (t0, t1) = ts.mesh.s_range, ts.mesh.t_range
    s, t = np.meshgrid(s0 + np.arange(ns) * (template.s_period_mm / ns), np.linspace(t0, t1, nt), indexing="ij")
    return ts.evaluate(s.ravel(), t.ravel()).points


def specificity_mm(model: ShapeModel, training: np.ndarray, modes: int, settings: ShapeModelSettings,
                   template: TemplateSettings) -> np.ndarray:
    """(samples,) for random shapes of the first ``modes`` modes (weights ~ N(0, sd^2), seeded): the RMS
    distance (mm) of each, over corresponding surface points, to the nearest aligned training shape."""
    rng = np.random.default_rng(settings.seed)
    k = min(modes, len(model.variances))
    train = np.stack([grid_points(s, template) for s in align(training, model.alignment)])
    out = np.empty(settings.specificity_samples)
    for i in range(settings.specificity_samples):
        sample = grid_points(model.shape(rng.standard_normal(k) * model.sd[:k]), template)
        out[i] = np.sqrt(np.mean(np.sum((train - sample) ** 2, axis=2), axis=1)).min()
    return out


def grid_triangles(ns: int = 48, nt: int = 120) -> np.ndarray:
    """(2 ns (nt - 1), 3) triangles over the points of ``grid_points`` (periodic in s), outward as the template."""
    i, j = np.meshgrid(np.arange(ns), np.arange(nt - 1), indexing="ij")
    a = (i * nt + j).ravel()
    b = (((i + 1) % ns) * nt + j).ravel()
    return np.concatenate([np.stack([a, b, b + 1], axis=1), np.stack([a, b + 1, a + 1], axis=1)])


def normal_offsets(mean_points: np.ndarray, points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(n,) signed offset (mm) of corresponding surface points from the mean's along its outward vertex normals."""
    from bonecad.mesh.closest import vertex_normals

    return np.einsum("ij,ij->i", points - mean_points, vertex_normals(mean_points, triangles))
