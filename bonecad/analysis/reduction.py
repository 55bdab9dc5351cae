"""Virtual fracture reduction: each fragment moved rigidly onto a template of the intact bone, then all together.

The template is the intact bone's shape: the other side's bone mirrored about its own sagittal plane
(``mirrored``). Every fragment is registered onto it in the template's coordinates:

1. a start: the fragment's long axis laid along the template's, the end it carries (proximal or distal: the end
   away from the other main fragment) on the template's end, at ``start_turns`` turns about the axis;
2. a robust point-to-plane ICP from each start (points whose nearest template point is far, beyond three robust
   standard deviations, or faces another way are left out), the start with the smallest trimmed RMS kept;
3. its fracture faces found (far from the template surface, or facing across it, in the half towards the
   fracture) and left out: the ICP again on its periosteal surface only;
4. the fragments refined together: each fragment's periosteal points pulled onto the template and its fracture
   points onto its neighbours' fracture surfaces (``contact_share`` of the weight for the main fragments, off
   by default; ``intermediate_contact_share`` for a butterfly, whose small periosteal patch on a round shaft
   leaves its place along and about the axis loose), so the fragments neither overlap nor leave gaps beyond
   the fracture's own.

Length, axis alignment and torsion therefore come from the template (and, across a fracture that interlocks,
from the fragments' contact). Results are in the input's coordinates with the proximal fragment where it lies.
Lengths in mm, angles in degrees.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from bonecad.errors import FitError
from bonecad.imaging.fracture import AxialFrame, apply, axial_frame
from bonecad.settings import FractureSettings

MAIN_ROLES = ("proximal", "distal")
#: fragments whose fracture surfaces come this near (mm) after reduction are neighbours (their gap reported)
NEIGHBOUR_REACH_MM = 10.0


@dataclass(frozen=True)
class Template:
    """The intact bone's shape the fragments are moved onto: a closed mesh (mm, outward faces) in its own
    coordinates, what it is (``kind``: "contralateral", "model"; ``source``) and its expected uncertainty
    (mm, degrees: how far the patient's own bone may be from it)."""

    vertices: np.ndarray
    faces: np.ndarray
    kind: str
    source: str
    uncertainty_mm: float
    uncertainty_deg: float


@dataclass(frozen=True)
class FragmentBody:
    """One fragment as found in the input: vertices (mm), faces (outward), role ("proximal", "distal",
    "intermediate")."""

    vertices: np.ndarray
    faces: np.ndarray
    role: str


@dataclass(frozen=True)
class Contact:
    """How a fragment meets a neighbour after reduction: the neighbour's index, the deepest overlap (mm, the
    99th percentile of the depth of its points inside the neighbour), the median gap (mm) across the fracture
    where the fracture surfaces face each other, and the share of its fracture surface within 0.5 mm of the
    neighbour's."""

    neighbour: int
    overlap_mm: float
    gap_mm: float
    contact_share: float


@dataclass(frozen=True)
class ReducedFragment:
    """One fragment reduced: role, ``transform`` (4 x 4, input coordinates: from where it lies to its reduced
    place), the move of its centroid (mm) and its rotation (degrees), the registration's RMS (mm, periosteal
    points kept) and share of its periosteal points kept, its fracture faces (m,) bool, its extent along the
    reduced bone's long axis (mm from the distal end) and its contacts."""

    role: str
    transform: np.ndarray
    translation_mm: float
    rotation_deg: float
    rms_mm: float
    inlier_share: float
    fracture: np.ndarray
    axial_extent_mm: tuple[float, float]
    contacts: tuple[Contact, ...]
    poor: bool


@dataclass(frozen=True)
class Reduction:
    """The reduced fracture: the fragments (input order), the template, the fracture lines' positions along the
    long axis (mm from the reduced bone's distal end: (lowest, highest, mean) of the fracture surfaces where
    two fragments meet), the long axis (unit, proximal, input coordinates) and notes for the user."""

    fragments: tuple[ReducedFragment, ...]
    template: Template
    fracture_levels_mm: tuple[tuple[float, float, float], ...]
    up: np.ndarray
    template_to_input: np.ndarray
    notes: tuple[str, ...] = field(default=())

    def reduced_meshes(self, bodies: list[FragmentBody]) -> list[tuple[np.ndarray, np.ndarray]]:
        """The fragments moved to their reduced places (vertices, faces)."""
        return [(apply(f.transform, b.vertices), b.faces) for f, b in zip(self.fragments, bodies)]


def mirrored(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, normal: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """A mesh mirrored about the plane through ``origin`` with unit ``normal``, faces turned to stay outward."""
    normal = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    offsets = (vertices - origin) @ normal
    return vertices - 2.0 * offsets[:, None] * normal, faces[:, ::-1].copy()


# --- surfaces as points ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Samples:
    """Points on a surface (mm), their unit normals and the face each lies on."""

    points: np.ndarray
    normals: np.ndarray
    faces: np.ndarray

    def subset(self, keep: np.ndarray) -> _Samples:
        return _Samples(self.points[keep], self.normals[keep], self.faces[keep])

    def moved(self, transform: np.ndarray) -> _Samples:
        return _Samples(apply(transform, self.points), self.normals @ transform[:3, :3].T, self.faces)


def _face_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (m, 3) and areas (m,) (mm^2) of the faces."""
    cross = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    norm = np.linalg.norm(cross, axis=1)
    return cross / np.maximum(norm, 1e-12)[:, None], 0.5 * norm


def _sample(vertices: np.ndarray, faces: np.ndarray, spacing_mm: float, seed: int = 0, most: int = 400_000
            ) -> _Samples:
    """About one point per ``spacing_mm`` squared of the surface (at most ``most``), uniform by area (seeded)."""
    normals, areas = _face_normals(vertices, faces)
    count = int(np.clip(areas.sum() / spacing_mm**2, 50, most))
    rng = np.random.default_rng(seed)
    chosen = rng.choice(len(faces), size=count, p=areas / areas.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    a, b, c = (vertices[faces[chosen, k]] for k in range(3))
    points = (1 - s)[:, None] * a + (s * (1 - r2))[:, None] * b + (s * r2)[:, None] * c
    return _Samples(points, normals[chosen], chosen)


@dataclass(frozen=True)
class _Target:
    """The template's surface as dense samples and their tree."""

    samples: _Samples
    tree: cKDTree
    frame: AxialFrame


def _target(vertices: np.ndarray, faces: np.ndarray, spacing_mm: float, bone: str) -> _Target:
    samples = _sample(vertices, faces, spacing_mm)
    return _Target(samples, cKDTree(samples.points), axial_frame(vertices, faces, bone))  # type: ignore[arg-type]


# --- rigid motions ------------------------------------------------------------------------------------------

def _rotation_vector(omega: np.ndarray) -> np.ndarray:
    angle = float(np.linalg.norm(omega))
    if angle < 1e-15:
        return np.eye(3)
    k = omega / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * (kx @ kx)


def rotation_deg(transform: np.ndarray) -> float:
    """The rotation angle (degrees) of a 4 x 4 or 3 x 3 rigid transform."""
    rot = transform[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0))))


def kabsch(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """4 x 4 rigid transform taking ``source`` points (n, 3) nearest to ``target`` (n, 3) in least squares."""
    cs, ct = source.mean(axis=0), target.mean(axis=0)
    u, _, vt = np.linalg.svd((source - cs).T @ (target - ct))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = ct - rot @ cs
    return out


def _align(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """3 x 3 rotation taking unit vector ``a`` to unit vector ``b`` (the shortest)."""
    v = np.cross(a, b)
    c = float(a @ b)
    if np.linalg.norm(v) < 1e-12:
        if c > 0:
            return np.eye(3)
        helper = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
        axis = np.cross(a, helper)
        return _rotation_vector(np.pi * axis / np.linalg.norm(axis))
    return _rotation_vector(np.arctan2(np.linalg.norm(v), c) * v / np.linalg.norm(v))


def _step(points: np.ndarray, residuals: np.ndarray, normals: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The 4 x 4 small rigid motion minimising sum w (r + (omega x p + t) . n)^2 (one Gauss-Newton step)."""
    a = np.concatenate([np.cross(points, normals), normals], axis=1)
    aw = a * weights[:, None]
    lhs = a.T @ aw + 1e-9 * np.eye(6)
    x = np.linalg.solve(lhs, -(aw.T @ residuals))
    out = np.eye(4)
    out[:3, :3] = _rotation_vector(x[:3])
    out[:3, 3] = x[3:]
    return out


@dataclass(frozen=True)
class _Fit:
    transform: np.ndarray
    rms: float
    inliers: float  # share of the points kept
    score: float  # the start's figure of merit: trimmed RMS over the share kept


def _matches(samples: _Samples, target: _Target, transform: np.ndarray, floor_mm: float, normal_cos: float
             ) -> tuple[_Samples, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The moved samples, their point-to-plane residuals (mm) to the nearest template point, its normal, and
    which are kept (near: within max(floor, 3 robust SDs), facing the same way), the distances (mm)."""
    moved = samples.moved(transform)
    dist, idx = target.tree.query(moved.points)
    normals = target.samples.normals[idx]
    residuals = np.einsum("ij,ij->i", moved.points - target.samples.points[idx], normals)
    facing = np.einsum("ij,ij->i", moved.normals, normals) > normal_cos
    pool = dist[facing] if facing.any() else dist
    limit = max(floor_mm, 3.0 * 1.4826 * float(np.median(pool)))
    return moved, residuals, normals, facing & (dist < limit), dist


def _icp(samples: _Samples, target: _Target, start: np.ndarray, settings: FractureSettings,
         iterations: int | None = None) -> _Fit:
    """Robust point-to-plane ICP of ``samples`` onto the template from ``start`` (4 x 4)."""
    transform = start
    for _ in range(iterations or settings.icp_iterations):
        moved, residuals, normals, kept, _ = _matches(samples, target, transform, settings.trim_floor_mm,
                                                      settings.normal_cos)
        if kept.sum() < 12:
            break
        step = _step(moved.points[kept], residuals[kept], normals[kept], np.ones(int(kept.sum())))
        transform = step @ transform
        if np.linalg.norm(step[:3, 3]) < 1e-4 and rotation_deg(step) < 1e-4:
            break
    _, residuals, _, kept, _ = _matches(samples, target, transform, settings.trim_floor_mm, settings.normal_cos)
    share = float(kept.mean())
    rms = float(np.sqrt(np.mean(residuals[kept] ** 2))) if kept.any() else np.inf
    return _Fit(transform, rms, share, rms / max(share, 1e-3) ** 2)


# --- the starts ---------------------------------------------------------------------------------------------

def _end_point(points: np.ndarray, direction: np.ndarray, band_mm: float) -> np.ndarray:
    """The mean of the points within ``band_mm`` of the extreme along ``direction``."""
    heights = points @ direction
    return points[heights > heights.max() - band_mm].mean(axis=0)


def _main_starts(body: _Samples, outward: np.ndarray, target: _Target, proximal: bool, turns: int,
                 band_mm: float) -> list[np.ndarray]:
    """Starts of a main fragment: its ``outward`` axis (unit, towards the end it carries) along the template's
    axis, that end on the template's end, at ``turns`` angles about the axis."""
    frame = target.frame
    towards = frame.up if proximal else -frame.up
    base = _align(outward, towards)
    end_template = _end_point(target.samples.points, towards, band_mm)
    starts = []
    for k in range(turns):
        rot = _rotation_vector(2 * np.pi * k / turns * towards) @ base
        end_fragment = _end_point(body.points @ rot.T, towards, band_mm)
        start = np.eye(4)
        start[:3, :3] = rot
        start[:3, 3] = end_template - end_fragment
        starts.append(start)
    return starts


def _outward_axis(points: np.ndarray, other_centre: np.ndarray) -> np.ndarray:
    """A fragment's principal axis, pointing away from ``other_centre`` (the other main fragment)."""
    centred = points - points.mean(axis=0)
    _, _, vt = np.linalg.svd(centred[:: max(1, len(points) // 5000)], full_matrices=False)
    axis = vt[0]
    return axis if (points.mean(axis=0) - other_centre) @ axis > 0 else -axis


def _fracture_faces(vertices: np.ndarray, faces: np.ndarray, target: _Target, transform: np.ndarray,
                    rms: float, outward: np.ndarray | None, settings: FractureSettings) -> np.ndarray:
    """(m,) bool the faces of a registered fragment that are not the template's surface: their centres far
    from it (beyond ``fracture_distance_mm`` or three RMS) or facing across it, and, for a main fragment, in its
    half towards the fracture (away from ``outward``)."""
    normals, _ = _face_normals(vertices, faces)
    centres = vertices[faces].mean(axis=1)
    moved = apply(transform, centres)
    dist, idx = target.tree.query(moved)
    facing = np.einsum("ij,ij->i", normals @ transform[:3, :3].T, target.samples.normals[idx])
    off = (dist > max(settings.fracture_distance_mm, 3.0 * rms)) | (facing < settings.normal_cos)
    if outward is not None:
        heights = (centres - centres.mean(axis=0)) @ outward
        off &= heights < 0.5 * (heights.max() + heights.min())
    return off


# --- the reduction ------------------------------------------------------------------------------------------

def _registered(body: FragmentBody, samples: _Samples, target: _Target, starts: list[np.ndarray],
                outward: np.ndarray | None, settings: FractureSettings) -> tuple[_Fit, np.ndarray, _Samples]:
    """The best start's fit of one fragment, its fracture faces, and its periosteal samples."""
    few = samples.subset(np.arange(len(samples.points))[:: max(1, len(samples.points) // settings.start_points)])
    coarse = [_icp(few, target, s, settings, settings.start_iterations) for s in starts]
    best = min(coarse, key=lambda f: f.score)
    fit = _icp(samples, target, best.transform, settings)
    fracture = _fracture_faces(body.vertices, body.faces, target, fit.transform, fit.rms, outward, settings)
    periosteal = samples.subset(~fracture[samples.faces])
    if len(periosteal.points) >= 50:
        fit = _icp(periosteal, target, fit.transform, settings)
    return fit, fracture, periosteal


def reduce_fragments(bodies: list[FragmentBody], template: Template, settings: FractureSettings, *,
                     bone: str = "tibia") -> Reduction:
    """Every fragment moved onto the template (module docstring). ``bodies`` hold one "proximal" and one
    "distal" fragment and any "intermediate" ones.

    Raises FitError when a main fragment is missing; a fragment that registers poorly (RMS beyond
    ``poor_rms_mm`` or fewer than ``poor_inlier_share`` of its periosteal points kept) is flagged ``poor``
    and named in the notes, never silently placed."""
    roles = [b.role for b in bodies]
    if roles.count("proximal") != 1 or roles.count("distal") != 1:
        raise FitError(f"a reduction needs one proximal and one distal fragment, got roles {roles}")
    target = _target(template.vertices, template.faces, settings.template_spacing_mm, bone)
    samples = [_sample(b.vertices, b.faces, settings.fragment_spacing_mm, seed=i, most=settings.fragment_points)
               for i, b in enumerate(bodies)]
    centres = [s.points.mean(axis=0) for s in samples]
    p, d = roles.index("proximal"), roles.index("distal")
    band = settings.end_band_share * target.frame.length
    fits: list[_Fit] = [None] * len(bodies)  # type: ignore[list-item]
    fractures: list[np.ndarray] = [np.zeros(0, bool)] * len(bodies)
    periosteal: list[_Samples] = list(samples)
    for i, other in ((p, d), (d, p)):
        outward = _outward_axis(samples[i].points, centres[other])
        starts = _main_starts(samples[i], outward, target, i == p, settings.start_turns, band)
        fits[i], fractures[i], periosteal[i] = _registered(bodies[i], samples[i], target, starts, outward, settings)
    for i, body in enumerate(bodies):
        if i in (p, d):
            continue
        starts = _intermediate_starts(centres[i], target, [fits[p].transform, fits[d].transform], settings)
        fits[i], fractures[i], periosteal[i] = _registered(body, samples[i], target, starts, None, settings)
    transforms = [f.transform for f in fits]
    fracture_samples = [s.subset(fr[s.faces]) for s, fr in zip(samples, fractures)]
    shares = [settings.contact_share if i in (p, d) else settings.intermediate_contact_share
              for i in range(len(bodies))]
    if max(shares) > 0:
        transforms = _refined_together(transforms, periosteal, fracture_samples, target, shares, settings)
    finals = [_icp(periosteal[i], target, t, settings, 1) for i, t in enumerate(transforms)]
    anchor = np.linalg.inv(transforms[p])
    to_input = [anchor @ t for t in transforms]
    up = anchor[:3, :3] @ target.frame.up
    reduced_samples = [s.moved(t) for s, t in zip(samples, to_input)]
    bottom = min(float((s.points @ up).min()) for s in reduced_samples)
    contacts, levels = _contacts([(apply(t, b.vertices), b.faces) for t, b in zip(to_input, bodies)],
                                 reduced_samples, [fs.moved(t) for fs, t in zip(fracture_samples, to_input)],
                                 up, bottom, settings)
    fragments, notes = [], []
    for i, body in enumerate(bodies):
        move = to_input[i]
        centre = body.vertices.mean(axis=0)
        heights = reduced_samples[i].points @ up - bottom
        poor = finals[i].rms > settings.poor_rms_mm or finals[i].inliers < settings.poor_inlier_share
        if poor:
            notes.append(f"fragment {i + 1} ({body.role}) registers poorly onto the template: RMS "
                         f"{finals[i].rms:.2f} mm, {100 * finals[i].inliers:.0f} % of its periosteal surface within "
                         "reach; check its place")
        fragments.append(ReducedFragment(
            role=body.role, transform=move, translation_mm=float(np.linalg.norm(apply(move, centre[None])[0] - centre)),
            rotation_deg=rotation_deg(move), rms_mm=finals[i].rms, inlier_share=finals[i].inliers,
            fracture=fractures[i], axial_extent_mm=(float(heights.min()), float(heights.max())),
            contacts=tuple(contacts[i]), poor=poor))
    notes.append(f"length, axis alignment and torsion come from the template ({template.kind}: {template.source}); "
                 f"expected uncertainty {template.uncertainty_mm:g} mm, {template.uncertainty_deg:g} degrees")
    return Reduction(tuple(fragments), template, tuple(levels), up, anchor, tuple(notes))


def _intermediate_starts(centre: np.ndarray, target: _Target, mains: list[np.ndarray], settings: FractureSettings
                         ) -> list[np.ndarray]:
    """Starts of an intermediate fragment: each main fragment's motion, then shifted along the template's
    axis by up to ``intermediate_search_mm`` and turned about it by up to 20 degrees about the fragment's
    place."""
    starts = []
    for main in mains:
        placed = apply(main, centre[None])[0]
        for shift in np.linspace(-settings.intermediate_search_mm, settings.intermediate_search_mm, 5):
            for turn in (-20.0, 0.0, 20.0):
                rot = _rotation_vector(np.radians(turn) * target.frame.up)
                move = np.eye(4)
                move[:3, :3] = rot
                move[:3, 3] = placed - rot @ placed + shift * target.frame.up
                starts.append(move @ main)
    return starts


def _refined_together(transforms: list[np.ndarray], periosteal: list[_Samples], fracture: list[_Samples],
                      target: _Target, shares: list[float], settings: FractureSettings) -> list[np.ndarray]:
    """All fragments refined in turn: periosteal points onto the template, fracture points onto the other
    fragments' fracture surfaces (within ``contact_mm``, facing them), the contact carrying ``shares[i]`` of
    fragment i's weight (a fragment of share 0 stays where the template puts it)."""
    transforms = list(transforms)
    for _ in range(settings.joint_rounds):
        for i in range(len(transforms)):
            share = shares[i]
            if share <= 0:
                continue
            moved, residuals, normals, kept, _ = _matches(periosteal[i], target, transforms[i],
                                                          settings.trim_floor_mm, settings.normal_cos)
            parts = [(moved.points[kept], residuals[kept], normals[kept],
                      np.full(int(kept.sum()), (1 - share) / max(int(kept.sum()), 1)))]
            mine = fracture[i].moved(transforms[i])
            others = [fracture[j].moved(transforms[j]) for j in range(len(transforms)) if j != i]
            others = [o for o in others if len(o.points)]
            if len(mine.points) and others:
                pool = _Samples(np.concatenate([o.points for o in others]), np.concatenate([o.normals for o in others]),
                                np.zeros(sum(len(o.points) for o in others), dtype=np.int64))
                dist, idx = cKDTree(pool.points).query(mine.points)
                opposite = np.einsum("ij,ij->i", mine.normals, pool.normals[idx]) < -settings.normal_cos
                near = opposite & (dist < settings.contact_mm)
                if near.sum() >= 12:
                    res = np.einsum("ij,ij->i", mine.points[near] - pool.points[idx[near]], pool.normals[idx[near]])
                    parts.append((mine.points[near], res, pool.normals[idx[near]],
                                  np.full(int(near.sum()), share / int(near.sum()))))
            if sum(len(part[0]) for part in parts) < 12:
                continue
            points, res, nrm, w = (np.concatenate([part[k] for part in parts]) for k in range(4))
            transforms[i] = _step(points, res, nrm, w) @ transforms[i]
    return transforms


def _contacts(meshes: list[tuple[np.ndarray, np.ndarray]], samples: list[_Samples], fracture: list[_Samples],
              up: np.ndarray, bottom: float, settings: FractureSettings
              ) -> tuple[list[list[Contact]], list[tuple[float, float, float]]]:
    """Each reduced fragment's contacts with the others (those its fracture surface comes within
    ``NEIGHBOUR_REACH_MM`` of: exact signed distances to their meshes), and each touching pair's fracture level
    (mm from the distal end: lowest, highest, mean of the fracture surface facing the other)."""
    import igl

    contacts: list[list[Contact]] = [[] for _ in samples]
    levels = []
    for i, own in enumerate(fracture):
        for j, (vertices, faces) in enumerate(meshes):
            if i == j or not len(own.points):
                continue
            mesh = (np.ascontiguousarray(vertices, dtype=np.float64), np.ascontiguousarray(faces, dtype=np.int64))
            signed = igl.signed_distance(own.points, *mesh)[0]
            facing = np.abs(signed) < max(settings.contact_mm, NEIGHBOUR_REACH_MM)
            if facing.sum() < max(12, 0.05 * len(own.points)):
                continue
            depth = -igl.signed_distance(samples[i].points, *mesh)[0]
            overlap = max(0.0, float(np.percentile(depth, 99.5)))
            gap = float(np.median(np.maximum(signed[facing], 0.0)))
            contacts[i].append(Contact(j, overlap, gap, float((np.abs(signed) < 0.5).mean())))
            if i < j:
                heights = own.points[facing] @ up - bottom
                levels.append((float(heights.min()), float(heights.max()), float(heights.mean())))
    return contacts, levels


def placement_errors(intact: list[np.ndarray], placed: list[np.ndarray]) -> list[tuple[float, float]]:
    """Per fragment, how far its ``placed`` points (n_i, 3) are from their ``intact`` places (the same points in
    the intact bone), once the whole placed bone is aligned to the intact one (least squares over all points):
    the mean distance (mm) and the fragment's own remaining rotation (degrees)."""
    whole = kabsch(np.concatenate(placed), np.concatenate(intact))
    errors = []
    for a, b in zip(placed, intact):
        moved = apply(whole, a)
        errors.append((float(np.linalg.norm(moved - b, axis=1).mean()), rotation_deg(kabsch(moved, b))))
    return errors


def ideal_placement(intact: list[tuple[np.ndarray, np.ndarray, np.ndarray]], template: Template,
                    settings: FractureSettings, *, bone: str = "tibia") -> list[np.ndarray]:
    """Where the best registration onto ``template`` puts each fragment, given its place in the intact bone and
    its true periosteal surface: ``intact`` holds (vertices, faces, fracture faces (m,) bool) per fragment at
    its intact place; the whole intact bone is registered first, then each fragment from there. The yardstick
    of a reduction onto a template that is not the patient's bone (the template's own cost). 4 x 4 per
    fragment, from its intact place."""
    target = _target(template.vertices, template.faces, settings.template_spacing_mm, bone)
    whole_vertices = np.concatenate([v for v, _, _ in intact])
    offsets = np.cumsum([0] + [len(v) for v, _, _ in intact[:-1]])
    whole_faces = np.concatenate([f + o for (_, f, _), o in zip(intact, offsets)])
    periosteal = np.concatenate([~fr for _, _, fr in intact])
    whole = _sample(whole_vertices, whole_faces[periosteal], settings.fragment_spacing_mm,
                    most=4 * settings.fragment_points)
    own = axial_frame(whole_vertices, whole_faces, bone)  # type: ignore[arg-type]
    starts = _main_starts(whole, own.up, target, True, settings.start_turns,
                          settings.end_band_share * target.frame.length)
    few = whole.subset(np.arange(len(whole.points))[:: max(1, len(whole.points) // settings.start_points)])
    best = min((_icp(few, target, s, settings, settings.start_iterations) for s in starts), key=lambda f: f.score)
    start = _icp(whole, target, best.transform, settings).transform
    out = []
    for i, (v, f, fr) in enumerate(intact):
        samples = _sample(v, f[~fr], settings.fragment_spacing_mm, seed=i, most=settings.fragment_points)
        out.append(_icp(samples, target, start, settings).transform)
    return out


def template_fit_rms(bodies: list[FragmentBody], vertices: np.ndarray, faces: np.ndarray,
                     settings: FractureSettings, *, bone: str = "tibia") -> float:
    """The proximal fragment's registration RMS (mm) onto a candidate template (the same steps as
    ``reduce_fragments``): how well the template's shape fits the fragments, to tell a template of the same side
    left unmirrored (it fits the mirrored one far better) or of another bone (it fits neither)."""
    roles = [b.role for b in bodies]
    p, d = roles.index("proximal"), roles.index("distal")
    target = _target(vertices, faces, settings.template_spacing_mm, bone)
    samples = _sample(bodies[p].vertices, bodies[p].faces, settings.fragment_spacing_mm,
                      most=settings.fragment_points)
    outward = _outward_axis(samples.points, bodies[d].vertices.mean(axis=0))
    starts = _main_starts(samples, outward, target, True, settings.start_turns,
                          settings.end_band_share * target.frame.length)
    fit, _, _ = _registered(bodies[p], samples, target, starts, outward, settings)
    return fit.rms
