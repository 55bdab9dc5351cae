"""CT volume -> the tibia's surface mesh (LPS world mm).

Steps: a Hounsfield threshold half-way between cortical bone and soft tissue;
connected bodies; the tibia chosen by shape (the long body; a fibula lies
beside it, femur and talus in series with it); morphological closing and the
marrow cavity filled; marching cubes on the grey values (sub-voxel surface) in
index space, mapped to world by the affine; Taubin smoothing (no shrinkage);
optional quadric decimation.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy import ndimage

from bonecad.errors import InputError
from bonecad.imaging.volume import CTVolume
from bonecad.mesh.bodies import BodyShape, body_roles, body_shape, neck_index
from bonecad.mesh.bone_mesh import BodyInfo, BoneMesh
from bonecad.settings import ImagingSettings, MeshSettings

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class _Body:
    label: int
    voxels: int
    volume_mm3: float
    centroid: np.ndarray  # (3,) LPS mm
    axis: np.ndarray  # (3,) unit principal direction
    length_mm: float
    slices: tuple  # bounding box in the cropped array
    shape: BodyShape  # what the intake's anatomy rules read (``bonecad.mesh.bodies``)


def surface_level(volume: CTVolume, settings: ImagingSettings) -> float:
    """Automatic bone surface level, HU: half-way between cortical bone and soft tissue."""
    return _levels(volume, settings)[0]


def _levels(volume: CTVolume, settings: ImagingSettings) -> tuple[float, float]:
    """(surface level, soft tissue value), HU, estimated from a 1-in-8 sample of the voxels."""
    hu = volume.hu[::2, ::2, ::2]
    bone = hu[hu > settings.cortical_min_hu]
    if bone.size == 0:
        raise InputError(f"no bone found: no voxel above {settings.cortical_min_hu:.0f} HU", volume.source or None)
    cortical = float(np.percentile(bone, settings.cortical_percentile))
    low, high = settings.soft_tissue_hu
    soft = hu[(hu > low) & (hu < high)]
    tissue = float(np.median(soft)) if soft.size else 0.0
    return float(np.clip(0.5 * (cortical + tissue), *settings.level_range_hu)), tissue


def segment_bone(
    volume: CTVolume,
    *,
    settings: ImagingSettings,
    mesh_settings: MeshSettings,
    level_hu: float | None = None,
    target_faces: int | None = None,
) -> BoneMesh:
    """The tibia's closed outer surface from a CT volume.

    settings : the segmentation's levels, body rules, split of touching
        bones, growth and smoothing ([imaging])
    mesh_settings : the bodies' roles by anatomy and the neck rule of fused
        bones ([mesh] fused_neck_*): a talus or femur joined to the tibia
        through a joint space the voxels do not resolve is separated along
        the joint (``_split_at_neck``)
    level_hu : bone surface level, HU (None: half-way between the volume's
        cortical bone and soft tissue, clamped to [imaging] level_range_hu)
    target_faces : decimate to about this many triangles (None: keep all)

    Returns a BoneMesh in LPS world mm, normals outward. Raises InputError when
    no bone is found, when the tibia cannot be told apart, or when the tibia
    reaches the border of the volume (the volume holds only part of it).
    """
    path = volume.source or None
    scan_voxel_mm = volume.spacing_mm
    volume = working_grid(volume, settings)
    auto_level, tissue = _levels(volume, settings)
    level = auto_level if level_hu is None else float(level_hu)
    mask = volume.hu >= level
    box = _bounding_box(mask)
    if box is None:
        raise InputError(f"no bone found: no voxel above {level:.0f} HU", path)
    mask = mask[box]
    offset = np.array([s.start for s in box])  # (k, j, i)
    labels, count = ndimage.label(mask)
    del mask
    bodies = _bodies(labels, count, offset, volume, settings)
    if _split_touching(labels, count, bodies, volume, settings):
        bodies = _bodies(labels, int(labels.max()), offset, volume, settings)
    tibia, fibulae = _pick_tibia(bodies, path, settings)
    separated: tuple[str, ...] = ()
    at_neck: list[int] = []  # labels of the bones separated at a neck (joints across the tibia's axis)
    for _ in range(2):  # a talus at the ankle, a femur at the knee
        found = _split_at_neck(labels, tibia, offset, volume, settings, mesh_settings)
        if found is None:
            break
        separated += (found[0],)
        at_neck.append(found[1])
        bodies = _bodies(labels, int(labels.max()), offset, volume, settings)
        tibia, fibulae = _pick_tibia(bodies, path, settings)
    parted = _split_at_marrow(labels, tibia, offset, volume, level, settings)
    if parted:
        bodies = _bodies(labels, int(labels.max()), offset, volume, settings)
        tibia, fibulae = _pick_tibia(bodies, path, settings)
        others = [b for b in bodies if b.label in parted and b is not tibia]
        separated += tuple(_parted_name(b, tibia) for b in others)
        at_neck += [b.label for b in others]
    _check_whole(tibia, offset, volume, path)

    # The tibia's box in the volume, padded by 2 voxels (HU beyond the volume: far below the level).
    sub = tuple(slice(max(s.start - 2, 0), s.stop + 2) for s in tibia.slices)
    own = np.pad(labels[sub] == tibia.label, 2)
    other = np.pad((labels[sub] != tibia.label) & (labels[sub] > 0), 2)
    jointed = np.pad(np.isin(labels[sub], at_neck), 2)
    del labels
    sub_offset = offset + np.array([s.start for s in sub]) - 2
    field = np.full(own.shape, level - 1000.0, dtype=np.float32)
    source = tuple(slice(o, o + n) for o, n in zip(sub_offset, own.shape))
    clipped = tuple(slice(max(s.start, 0), min(s.stop, n)) for s, n in zip(source, volume.shape))
    dest = tuple(slice(c.start - s.start, c.stop - s.start) for c, s in zip(clipped, source))
    field[dest] = volume.hu[clipped]

    # Grow the tibia into voxels above half-way between tissue and the level
    # (closes a thin, partial-volumed cortex), close, fill the marrow; never
    # near a neighbour's voxels (a talus dome separated from the plafond lies
    # inside the tibia's rim in the slices through the joint; a joint space
    # thinner than a voxel is bright with both bones' partial volume).
    grow = settings.grow_voxels
    weak = (field >= 0.5 * (level + tissue)) & ~ndimage.binary_dilation(other, iterations=grow)
    own |= ndimage.binary_dilation(own, iterations=grow, mask=weak)
    del weak
    own = ndimage.binary_closing(own, structure=ndimage.generate_binary_structure(3, 1), iterations=1)
    own = _fill_holes(own)
    own = _fill_cross_sections(own, tibia.axis, volume) & ~other

    # Grey values for marching cubes: the interior lifted above the level (marrow
    # filled), everything away from the tibia pushed below it (no fibula).
    joint = _joint_midway(field, own, jointed, level, volume.spacing_mm[::-1], settings)
    del jointed
    interior = ndimage.binary_erosion(own)
    field[interior] = np.maximum(field[interior], level + 500.0)
    near = ndimage.binary_dilation(own, iterations=2)
    field[~near] = np.minimum(field[~near], level - 500.0)
    # Voxels of a touching bone (split off from the tibia) stay outside.
    cut = other & ~own
    field[cut] = np.minimum(field[cut], level - 500.0)
    if joint is not None:
        field[joint[0]] = joint[1]
    field[[0, -1], :, :] = field[:, [0, -1], :] = field[:, :, [0, -1]] = level - 1000.0
    del interior, near, own, other, cut

    mesh = _surface(field, level, sub_offset, volume, settings.slice_spline_degree)
    del field
    mesh = _largest_part(mesh)
    if settings.smoothing_iterations > 0:
        import trimesh

        trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=0.53, iterations=settings.smoothing_iterations)
    if target_faces is not None and len(mesh.faces) > target_faces:
        mesh = _decimate(mesh, target_faces)
    if mesh.volume < 0:
        mesh.invert()
    infos = tuple(
        BodyInfo(
            triangles=len(mesh.faces) if b is tibia else 0,
            volume_mm3=b.volume_mm3,
            length_mm=b.length_mm,
            centroid=b.centroid,
            role=role,
        )
        for b, role in _named_bodies(bodies, tibia, fibulae, mesh_settings, offset, volume.shape)
    )
    return BoneMesh(
        vertices=np.asarray(mesh.vertices, dtype=np.float64),
        faces=np.asarray(mesh.faces, dtype=np.int64),
        source=volume.source,
        bodies=infos,
        repairs=separated,
        watertight=bool(mesh.is_watertight),
        segmented=True,
        extra={"level_hu": level, "voxel_mm": volume.spacing_mm.tolist(), "scan_voxel_mm": scan_voxel_mm.tolist()},
    )


def _joint_midway(field: np.ndarray, own: np.ndarray, other: np.ndarray, level: float, spacing_kji: np.ndarray,
                  settings: ImagingSettings) -> tuple[np.ndarray, np.ndarray] | None:
    """Where the tibia (``own``, solid) touches a bone separated from it at a neck (``other``: talus, femur):
    the voxels on both sides of the contact and their grey values capped so the surface runs half-way
    between the two bones' marrow.

    A joint space thinner than a slice is one bright band of both bones' cortices; the neck's watershed
    gives the whole band to one side. The joint lies between the two subchondral plates, half-way between
    the marrow on either side (voxels below the level inside each bone, not within
    ``settings.joint_space_mm`` of the other bone): a contact voxel's value is capped at
    ``level + gain * (distance to the neighbour's marrow - distance to the tibia's)``, so the surface passes
    where both distances are equal; only where both marrows lie within ``settings.joint_reach_mm`` (a bone
    without marrow in reach keeps the watershed's part). Not beside the fibula: the tibia's rim over the
    fibular head is a thin lip without marrow of its own, and half-way between the marrows lies in it (TLEM2
    at 0.7 x 0.7 x 2.0 mm: worst miss 1.54 -> 1.64 mm). Returns (mask, values) or None.
    """
    contact = (own & ndimage.binary_dilation(other)) | (other & ndimage.binary_dilation(own))
    if not contact.any():
        return None
    box = _bounding_box(contact)
    assert box is not None
    reach = settings.joint_reach_mm
    pad = np.ceil(reach / spacing_kji).astype(int) + 1
    box = tuple(slice(max(s.start - p, 0), min(s.stop + p, n)) for s, p, n in zip(box, pad, own.shape))
    grey, mine, theirs = field[box], own[box], other[box]
    low = grey < level
    # marrow: dark voxels inside a bone, not the joint space the filling closed in beside the other one
    apart = settings.joint_space_mm
    mine_marrow = mine & low & (ndimage.distance_transform_edt(~theirs, sampling=spacing_kji) > apart)
    theirs_marrow = theirs & low & (ndimage.distance_transform_edt(~mine, sampling=spacing_kji) > apart)
    to_mine = ndimage.distance_transform_edt(~mine_marrow, sampling=spacing_kji)
    to_theirs = ndimage.distance_transform_edt(~theirs_marrow, sampling=spacing_kji)
    where = contact[box] & (to_mine <= reach) & (to_theirs <= reach)
    if not where.any():
        return None
    mask = np.zeros(own.shape, dtype=bool)
    mask[box] = where
    values = np.minimum(grey[where], level + settings.joint_gain_hu_per_mm * (to_theirs[where] - to_mine[where]))
    return mask, values


def working_grid(volume: CTVolume, settings: ImagingSettings) -> CTVolume:
    """``volume`` averaged over blocks of whole voxels, per axis the most whose edge stays within ``[imaging]
    working_voxel_mm``; ``volume`` itself where no axis has two voxels in that length. The mean keeps the
    surface's sub-voxel position (its partial volume) and lowers the noise, and the segmentation's cost falls
    with the blocks' volume."""
    factors = np.maximum(1, np.floor(settings.working_voxel_mm / volume.spacing_mm[::-1] + 1e-6)).astype(int)
    if np.all(factors == 1):
        return volume
    hu = _block_mean(volume.hu, factors, pad="edge")
    f_ijk = factors[::-1]
    affine = volume.affine.copy()
    affine[:3, :3] = volume.affine[:3, :3] * f_ijk
    affine[:3, 3] = volume.index_to_world(0.5 * (f_ijk - 1.0)[None])[0]  # the first block's centre
    log.info("segmenting on blocks of %d x %d x %d voxels (%.2f x %.2f x %.2f mm)",
             *f_ijk, *(volume.spacing_mm * f_ijk))
    missing = tuple(sorted({k // int(factors[0]) for k in volume.missing_slices}))
    return CTVolume(hu=hu, affine=affine, source=volume.source, missing_slices=missing)


def _bounding_box(mask: np.ndarray) -> tuple[slice, ...] | None:
    spans = []
    for axis in range(3):
        other = tuple(a for a in range(3) if a != axis)
        hit = np.flatnonzero(mask.any(axis=other))
        if hit.size == 0:
            return None
        spans.append(slice(int(hit[0]), int(hit[-1]) + 1))
    return tuple(spans)


def _bodies(labels: np.ndarray, count: int, offset: np.ndarray, volume: CTVolume, settings: ImagingSettings
            ) -> list[_Body]:
    """Size, centroid, principal axis and length (mm) of each labelled body above the fragment share."""
    sizes = np.bincount(labels.ravel(), minlength=count + 1)
    sizes[0] = 0
    if count == 0:
        return []
    voxel_mm3 = abs(np.linalg.det(volume.affine[:3, :3]))
    keep = np.flatnonzero(sizes >= settings.fragment_voxel_share * sizes.max())
    boxes = ndimage.find_objects(labels)
    bodies = []
    for label in keep:
        box = boxes[label - 1]
        step = max(1, int(round((sizes[label] / 2e5) ** (1 / 3))))
        part = labels[tuple(slice(s.start, s.stop, step) for s in box)] == label
        kji = np.argwhere(part) * step + np.array([s.start for s in box]) + offset
        xyz = volume.index_to_world(kji[:, ::-1])
        centroid = xyz.mean(axis=0)
        shape = body_shape(xyz, float(sizes[label] * voxel_mm3), centroid)
        bodies.append(
            _Body(
                label=int(label),
                voxels=int(sizes[label]),
                volume_mm3=shape.volume,
                centroid=centroid,
                axis=shape.axis,
                length_mm=shape.length,
                slices=box,
                shape=shape,
            )
        )
    return bodies


def _pick_tibia(bodies: list[_Body], path: object, settings: ImagingSettings) -> tuple[_Body, frozenset[int]]:
    """The tibia among the bodies, and the labels of the fibulae found beside a long bone.

    Long bodies are those at least ``settings.long_length_share`` as long as the longest. A long body
    lying beside a bulkier one (spans along the limb overlapping, centroids
    close across it) is a fibula.
    Of the remaining long bones in series (femur, tibia), the tibia is the one
    with a fibula beside it, else the one with bodies on both sides (femur
    above, talus below).
    """
    if not bodies:
        raise InputError("no bone found", path)
    longest = max(b.length_mm for b in bodies)
    biggest = max(bodies, key=lambda b: b.volume_mm3)
    limb = biggest.axis

    def span(b: _Body) -> tuple[float, float]:
        centre = b.centroid @ limb
        half = 0.5 * b.length_mm * abs(b.axis @ limb)
        return centre - half, centre + half

    def overlap(a: _Body, b: _Body) -> float:
        (a0, a1), (b0, b1) = span(a), span(b)
        shorter = min(a1 - a0, b1 - b0)
        return max(0.0, min(a1, b1) - max(a0, b0)) / shorter if shorter > 0 else 0.0

    def apart(a: _Body, b: _Body) -> float:
        gap = b.centroid - a.centroid
        return float(np.linalg.norm(gap - (gap @ limb) * limb))

    def beside(a: _Body, b: _Body) -> bool:
        return (overlap(a, b) >= settings.beside_overlap_share
                and apart(a, b) <= settings.beside_distance_share * max(a.length_mm, b.length_mm))

    long = [b for b in bodies if b.length_mm >= settings.long_length_share * longest]
    fibulae = {}
    for b in long:
        hosts = [a for a in long if a is not b and a.volume_mm3 > b.volume_mm3 and beside(a, b)]
        if hosts:
            fibulae[b.label] = min(hosts, key=lambda a: apart(a, b)).label
    main = [b for b in long if b.label not in fibulae]
    candidates = main
    if len(candidates) > 1:
        with_fibula = [b for b in candidates if b.label in fibulae.values()]
        if with_fibula:
            candidates = with_fibula
    if len(candidates) > 1:
        between = []
        for b in candidates:
            lo, hi = span(b)
            others = [(o.centroid @ limb) for o in bodies
                      if o is not b and overlap(o, b) < settings.beside_overlap_share]
            if any(c < lo for c in others) and any(c > hi for c in others):
                between.append(b)
        if len(between) == 1:
            candidates = between
    if len(candidates) != 1:
        raise InputError(
            f"cannot tell the tibia among {len(candidates)} long bones (both legs, or femur and tibia without "
            "fibula or talus); crop the volume to one lower leg",
            path,
        )
    return candidates[0], frozenset(fibulae)


def _named_bodies(bodies: list[_Body], tibia: _Body, fibulae: frozenset[int], settings: MeshSettings,
                  offset: np.ndarray, shape: tuple[int, ...]) -> list[tuple[_Body, str]]:
    """Every body with its role by anatomy (``bonecad.mesh.bodies.body_roles``, as a mesh's intake names
    them: femur, patella, talus, ...), the tibia first (the kept body, as in a mesh's intake). A fibula
    ``_pick_tibia`` found beside the tibia stays a fibula. The tibia's plateau end is the superior one (LPS z)."""
    ordered = [tibia, *(b for b in bodies if b is not tibia)]
    up = tibia.axis if tibia.axis[2] > 0 else -tibia.axis
    named = body_roles([b.shape for b in ordered], 0, up, settings)
    return [(b, "fibula" if b.label in fibulae else _cut_femur(b, role, tibia, up, offset, shape))
            for b, role in zip(ordered, named)]


def _cut_femur(body: _Body, role: str, tibia: _Body, up: np.ndarray, offset: np.ndarray, shape: tuple[int, ...]
               ) -> str:
    """``role``, or "femur" for a "broken piece" beyond the plateau that the volume's border cuts: the end of a
    femur in a knee-to-ankle field of view (the tibia itself is whole: ``_check_whole``), not a piece of the
    tibia."""
    if role != "broken piece" or float((body.centroid - tibia.centroid) @ up) <= 0.0:
        return role
    at_border = any(s.start + o == 0 or s.stop + o == n for s, o, n in zip(body.slices, offset, shape))
    return "femur" if at_border else role


def _check_whole(tibia: _Body, offset: np.ndarray, volume: CTVolume, path: object) -> None:
    """InputError when the tibia touches a face of the volume (only part of it was scanned)."""
    names = ("first/last slice (top or bottom of the volume)", "first/last row", "first/last column")
    for axis, s in enumerate(tibia.slices):
        start, stop = s.start + offset[axis], s.stop + offset[axis]
        if start == 0 or stop == volume.shape[axis]:
            raise InputError(
                f"the volume holds only part of the tibia: the bone reaches the {names[axis]}; "
                "scan or crop so the whole tibia lies inside the volume",
                path,
            )


def _array_axis_along(axis_world: np.ndarray, volume: CTVolume) -> int:
    """The array axis (0: k, 1: j, 2: i) nearest to a world direction."""
    steps = volume.affine[:3, :3] / volume.spacing_mm
    return 2 - int(np.argmax(np.abs(steps.T @ axis_world)))  # index axis 0: i, 1: j, 2: k


def _fill_cross_sections(mask: np.ndarray, axis_world: np.ndarray, volume: CTVolume) -> np.ndarray:
    """Fill holes in each cross-section perpendicular to the array axis nearest the bone's long axis."""
    array_axis = _array_axis_along(axis_world, volume)
    out = np.moveaxis(mask, array_axis, 0).copy()
    for n in range(out.shape[0]):
        if out[n].any():
            out[n] = _fill_holes(out[n])
    return np.moveaxis(out, 0, array_axis)


def _fill_holes(mask: np.ndarray) -> np.ndarray:
    """``mask`` with every background region not connected to the array's border filled (2-D or 3-D)."""
    background, _ = ndimage.label(~mask)
    border = np.zeros(mask.shape, dtype=bool)
    for axis in range(mask.ndim):
        index: list[slice | int] = [slice(None)] * mask.ndim
        for end in (0, -1):
            index[axis] = end
            border[tuple(index)] = True
    outside_labels = np.unique(background[border & ~mask])
    return ~np.isin(background, outside_labels) | mask


def _split_touching(labels: np.ndarray, count: int, bodies: list[_Body], volume: CTVolume,
                    settings: ImagingSettings) -> bool:
    """Split long bodies that are two bones touching (tibia and fibula at a joint), in place in ``labels``.

    The filled body is eroded on a grid of about 1 mm, up to ``settings.split_erode_mm``;
    if it falls into two or more long parts, every voxel of the filled body
    goes to the nearest part. Returns whether any body was split.
    """
    if not bodies:
        return False
    longest = max(b.length_mm for b in bodies)
    spacing_kji = volume.spacing_mm[::-1]
    factors = np.maximum(1, np.round(1.0 / spacing_kji)).astype(int)  # per array axis: blocks of about 1 mm
    split_any = False
    for body in bodies:
        if body.length_mm < settings.long_length_share * longest:
            continue
        region = labels[body.slices]
        own = region == body.label
        filled = _fill_holes(own)
        coarse = _block_mean(filled, factors) >= 0.5
        # Erosion by r mm: the coarse voxels deeper than r (exact Euclidean depth on an anisotropic grid).
        depth = ndimage.distance_transform_edt(coarse, sampling=factors * spacing_kji)
        parts = None
        for r in np.arange(1.0, settings.split_erode_mm + 0.5, 1.0):
            found, n = ndimage.label(depth > r)
            if n < 2:
                continue
            sizes = np.bincount(found.ravel())[1:]
            keep = [
                lab + 1
                for lab in np.flatnonzero(sizes >= settings.split_part_share * sizes.sum())
                if _part_length(found == lab + 1, factors, body, volume) >= settings.split_length_share * body.length_mm
            ]
            if len(keep) >= 2:
                parts = np.where(np.isin(found, keep), found, 0)
                break
        if parts is None:
            continue
        # Every voxel of the filled body goes to the nearest part (in mm), so each bone keeps a closed
        # cross-section, marrow too; the first part keeps the body's label.
        _, index = ndimage.distance_transform_edt(parts == 0, sampling=factors * spacing_kji, return_indices=True)
        nearest = parts[tuple(index)]
        for axis in range(3):
            nearest = np.repeat(nearest, factors[axis], axis=axis)
        nearest = nearest[: own.shape[0], : own.shape[1], : own.shape[2]]
        target = filled & ((region == 0) | own)
        first = nearest[target].min()
        new = np.where(nearest[target] == first, body.label, nearest[target] + count)
        region[target] = new
        count = int(new.max()) if new.max() > count else count
        split_any = True
        log.info("split a body of %.0f mm into touching bones", body.length_mm)
    return split_any


def _split_at_neck(labels: np.ndarray, tibia: _Body, offset: np.ndarray, volume: CTVolume,
                   settings: ImagingSettings, mesh_settings: MeshSettings) -> tuple[str, int] | None:
    """Separate a bone fused to one end of the tibia (talus at the ankle, femur at the knee), in place in
    ``labels``; returns what was separated (for the bone's repairs) and its new label, or None.

    A joint space thinner than a voxel (2 mm slices at the ankle) joins both
    bones in the threshold mask. Walking from each end of the filled body along
    its axis, the cross-section areas (``mesh_settings.fused_neck_*``) fall to a neck
    at the joint and rise again. A marker-controlled watershed of the depth
    below the body's surface then parts the two where the depth has its saddle,
    in the neck: one marker is the tibia beyond the neck's reach, the other the
    deep core of the bone beyond the neck (voxels at least half as deep as its
    deepest one, so a malleolus beside the talus stays with the tibia). The
    grey values cannot guide it: with slices as thick as the joint space, the
    joint's voxels are as bright as bone.
    """
    from skimage.segmentation import watershed

    region = labels[tibia.slices]
    own = region == tibia.label
    filled = _fill_cross_sections(own, tibia.axis, volume)  # solid sections, marrow and all
    kji = np.argwhere(filled)
    start = np.array([s.start for s in tibia.slices]) + offset
    heights = volume.index_to_world((kji + start)[:, ::-1].astype(np.float64)) @ tibia.axis
    low, high = float(heights.min()), float(heights.max())
    spacing_kji = volume.spacing_mm[::-1]
    # bins of whole slices along the axis (no aliasing between 1 and 2 slices a bin), at most 3 mm
    along = float(spacing_kji[_array_axis_along(tibia.axis, volume)])
    step = along * max(1, int(3.0 / along))
    voxel_mm3 = abs(float(np.linalg.det(volume.affine[:3, :3])))
    zone = mesh_settings.fused_neck_zone_share * (high - low)
    for end, sign in ((low, 1.0), (high, -1.0)):
        depth = sign * (heights - end)  # mm from this end, inwards
        bins = np.floor(depth / step).astype(np.int64)
        inside = depth < zone
        areas = np.bincount(bins[inside], minlength=int(zone // step) + 1) * voxel_mm3 / step
        k = neck_index(areas, mesh_settings.fused_neck_ratio)
        if k is None:
            continue
        neck_mm = (k + 0.5) * step
        beyond = depth < neck_mm - step
        near = depth > neck_mm + 2 * step
        if not beyond.any() or not near.any():
            continue
        distance = ndimage.distance_transform_edt(filled, sampling=spacing_kji)
        deep = distance[tuple(kji.T)]
        core_depth = 0.5 * deep[beyond].max()
        core = np.zeros(filled.shape, dtype=bool)
        core[tuple(kji[beyond & (deep >= core_depth)].T)] = True
        parts, _ = ndimage.label(core)
        deepest = tuple(kji[beyond][np.argmax(deep[beyond])])
        markers = np.zeros(filled.shape, dtype=np.int32)
        markers[parts == parts[deepest]] = 2
        markers[tuple(kji[near].T)] = 1
        second = watershed(-distance, markers, mask=filled) == 2
        share = float(second.sum()) / float(filled.sum())
        if share < settings.fragment_voxel_share:
            continue
        target = filled & ((region == 0) | own)
        new_label = int(labels.max()) + 1
        region[target & second] = new_label
        region[target & ~second] = tibia.label
        bone, end_name = ("talus", "distal") if _points_down(sign, tibia) else ("femur", "proximal")
        what = (f"separated the {bone} ({second.sum() * voxel_mm3 / 1000:.0f} cm3), fused to the tibia's "
                f"{end_name} end through a joint space the voxels do not resolve (neck {neck_mm:.0f} mm from "
                "the end)")
        log.info(what)
        return what, new_label
    return None


def _split_at_marrow(labels: np.ndarray, tibia: _Body, offset: np.ndarray, volume: CTVolume, level: float,
                     settings: ImagingSettings) -> list[int]:
    """Part the tibia's body between its marrow cavities, in place in ``labels``, when it holds more than one
    of at least ``settings.split_marrow_cm3``: a bone fused to it across a broad contact (the talus in the
    mortise, the condyles on the plateau, a fibula along the shaft) that shows no neck. Every bone keeps its
    cortex (subchondral plate) between its marrow and the joint, so the joint lies half-way between the two
    cavities: each voxel of the filled body goes to its nearest cavity. Returns the label of every part (the
    largest cavity's part keeps the body's label, first), or [] when the body has one cavity."""
    region = labels[tibia.slices]
    own = region == tibia.label
    filled = _fill_cross_sections(own, tibia.axis, volume)
    start = np.array([s.start for s in tibia.slices]) + offset
    grey = volume.hu[tuple(slice(a, a + n) for a, n in zip(start, filled.shape))]
    # marrow: dark voxels inside the filled body, one voxel in from it (no thin paths through a joint space)
    marrow = ndimage.binary_erosion(filled & (grey < level))
    cavities, count = ndimage.label(marrow)
    if count < 2:
        return []
    voxel_mm3 = abs(float(np.linalg.det(volume.affine[:3, :3])))
    sizes = np.bincount(cavities.ravel())[1:] * voxel_mm3
    big = np.flatnonzero(sizes >= 1000.0 * settings.split_marrow_cm3) + 1
    if len(big) < 2:
        return []
    markers = np.where(np.isin(cavities, big), cavities, 0)
    del cavities, marrow
    _, index = ndimage.distance_transform_edt(markers == 0, sampling=volume.spacing_mm[::-1], return_indices=True)
    nearest = markers[tuple(index)]
    del index
    target = filled & ((region == 0) | own)
    first = int(big[np.argmax(sizes[big - 1])])
    total = float(target.sum())
    parts: list[int] = []
    next_label = int(labels.max()) + 1
    for cavity in big:
        if cavity == first:
            continue
        part = target & (nearest == cavity)
        if float(part.sum()) < settings.fragment_voxel_share * total:
            continue
        region[part] = next_label
        parts.append(next_label)
        next_label += 1
    if parts:
        parts.insert(0, tibia.label)
        log.info("parted a body of %.0f mm between %d marrow cavities", tibia.length_mm, len(parts))
    return parts


def _parted_name(body: _Body, tibia: _Body) -> str:
    """What a bone parted from the tibia at its marrow is, by where it lies along the tibia: beyond its
    proximal or distal end (femur, talus), or beside it (fibula)."""
    up = tibia.axis if tibia.axis[2] > 0 else -tibia.axis
    height = float((body.centroid - tibia.centroid) @ up)
    bone = "femur" if height > 0.35 * tibia.length_mm else "talus" if height < -0.35 * tibia.length_mm else "fibula"
    return (f"separated the {bone} ({body.volume_mm3 / 1000:.0f} cm3), fused to the tibia across a broad contact "
            "(a joint space the voxels do not resolve), half-way between the two bones' marrow")


def _points_down(sign: float, tibia: _Body) -> bool:
    """Whether the end walked from (sign +1: the low end along ``tibia.axis``) is the lower one in z."""
    return (sign > 0) == (tibia.axis[2] > 0)


def _block_mean(values: np.ndarray, factors: np.ndarray, *, pad: Literal["constant", "edge"] = "constant"
                ) -> np.ndarray:
    """float32 mean of ``values`` over blocks of ``factors`` voxels per array axis, the array padded to a
    multiple of them with ``pad`` (numpy's mode: "constant", False or 0; "edge", the last slice repeated)."""
    if np.all(factors == 1):
        return values.astype(np.float32)
    widths = [(0, (-n) % f) for n, f in zip(values.shape, factors)]
    padded = np.pad(values, widths, mode=pad) if any(w for _, w in widths) else values
    total = padded
    for axis, f in enumerate(factors):  # strided sums, one axis at a time: no (n, f, ...) temporaries
        if f > 1:
            index: list[slice] = [slice(None)] * total.ndim
            index[axis] = slice(0, None, f)
            acc = total[tuple(index)].astype(np.float32)
            for r in range(1, f):
                index[axis] = slice(r, None, f)
                acc += total[tuple(index)]
            total = acc
    return total * np.float32(1.0 / np.prod(factors))


def _part_length(part: np.ndarray, factors: np.ndarray, body: _Body, volume: CTVolume) -> float:
    """Extent (mm) of a coarse part along the body's principal axis."""
    kji = np.argwhere(part) * factors
    xyz = volume.index_to_world(kji[:, ::-1].astype(np.float64))
    along = xyz @ body.axis
    return float(along.max() - along.min())


def _surface(field: np.ndarray, level: float, kji_offset: np.ndarray, volume: CTVolume, spline_degree: int):
    """Marching cubes of ``field`` at ``level``, vertices mapped to LPS world mm.

    Marching cubes interpolates linearly between voxel centres, which cuts the bone's curvature across thick
    slices: an axis whose spacing is n >= 2 times the finest (a 2 mm slice beside 0.7 mm pixels: 3) is first
    interpolated n-fold by a spline of ``spline_degree`` through the voxel centres (1: no interpolation)."""
    import trimesh
    from scipy.interpolate import make_interp_spline
    from skimage.measure import marching_cubes

    spacing = volume.spacing_mm[::-1]  # (k, j, i)
    factors = np.ones(3)
    for axis in range(3):
        n = int(round(spacing[axis] / spacing.min()))
        if n < 2 or spline_degree < 2 or field.shape[axis] <= spline_degree:
            continue
        centres = np.arange(field.shape[axis], dtype=np.float64)
        spline = make_interp_spline(centres, field, k=spline_degree, axis=axis)
        field = spline(np.arange((field.shape[axis] - 1) * n + 1) / n).astype(np.float32)
        factors[axis] = n
    verts, faces, _, _ = marching_cubes(field, level=level, allow_degenerate=False)
    ijk = (verts / factors + kji_offset)[:, ::-1]
    return trimesh.Trimesh(volume.index_to_world(ijk), faces, process=True)


def _largest_part(mesh):
    """The connected part of ``mesh`` with the most faces."""
    import trimesh

    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    biggest = np.argmax(np.bincount(labels))
    if np.all(labels == biggest):
        return mesh
    part = mesh.submesh([np.flatnonzero(labels == biggest)], append=True)
    return part


def _decimate(mesh, target_faces: int):
    """Quadric edge-collapse decimation to about ``target_faces`` triangles, topology kept."""
    import pymeshlab
    import trimesh

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(mesh.vertices), np.asarray(mesh.faces)))
    ms.meshing_decimation_quadric_edge_collapse(
        targetfacenum=int(target_faces), preservenormal=True, preservetopology=True, planarquadric=True
    )
    out = ms.current_mesh()
    return trimesh.Trimesh(out.vertex_matrix(), out.face_matrix(), process=True)
