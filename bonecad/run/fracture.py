"""``bonecad reduce``: a broken bone's fragments moved onto a template, written as reduced.stl, reduction.json
and reduction.png (all or nothing, ``staged_output``)."""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bonecad.analysis.reduction import (FragmentBody, apply, Reduction, Template, mirrored, reduce_fragments,
                                        template_fit_rms)
from bonecad.anatomy.recognise import recognise_bone
from bonecad.errors import BonecadError, InputError
from bonecad.mesh.fragments import BrokenBone, load_broken_bone
from bonecad.mesh.intake import Units, load_bone
from bonecad.render.fracture import reduction_png
from bonecad.run.bones import bone_frame
from bonecad.settings import Settings
from bonecad.staging import staged_output

log = logging.getLogger(__name__)

TEMPLATE_KINDS = ("contralateral", "model")


@dataclass(frozen=True)
class Reduced:
    """A reduction run's results: the broken bone read, its reduction, the template's side and bone."""

    broken: BrokenBone
    reduction: Reduction
    bone: str
    template_side: str


def contralateral_template(path: str | Path, settings: Settings, *, bone: str, units: Units = "auto"
                           ) -> tuple[Template, np.ndarray, np.ndarray, str, str]:
    """The other side's bone mirrored about its own sagittal plane (the plane through its frame's origin normal
    to its lateral axis): the template, the unmirrored vertices and faces, the bone it is and its side.

    InputError naming the file when it is not the bone asked for (``bone`` "auto": whichever it is)."""
    mesh = load_bone(path, units=units, settings=settings.mesh, plausible=settings.units,
                     keep="femur" if bone == "femur" else "tibia")
    found = recognise_bone(mesh, femur=settings.femur, plausible=settings.units, asked="auto")
    if bone not in ("auto", found):
        raise InputError(f"the template is a {found}, but the fragments are read as a {bone}: give the other "
                         f"side's {bone} (or --bone {found})", path)
    settings = settings.replace("pipeline", bone=found)
    frame = bone_frame(mesh, settings)
    vertices, faces = mirrored(np.asarray(mesh.vertices, dtype=np.float64), mesh.faces, frame.origin, frame.lateral)
    fr = settings.fracture
    template = Template(vertices, faces, "contralateral", f"{Path(path).name} ({frame.side} {found}, mirrored)",
                        fr.contralateral_uncertainty_mm, fr.contralateral_uncertainty_deg)
    return template, np.asarray(mesh.vertices, dtype=np.float64), mesh.faces, found, frame.side


def reduce_fracture(source: str | Path, template_kind: str, template_path: str | Path, settings: Settings, *,
                    units: Units = "auto") -> Reduced:
    """Read the broken bone and the template, check the template (the same bone, the other side), reduce."""
    if template_kind != "contralateral":
        raise InputError(f"--template {template_kind}: only 'contralateral MESH' templates are implemented "
                         "(the shape-model template is not yet)", template_path)
    template, plain_vertices, plain_faces, bone, side = contralateral_template(
        template_path, settings, bone=settings.pipeline.bone, units=units)
    broken = load_broken_bone(source, units=units, settings=settings.mesh, plausible=settings.units,
                              fracture=settings.fracture, bone=bone)  # type: ignore[arg-type]
    log.info("%s", broken.describe())
    bodies = [FragmentBody(p.vertices, p.faces, p.role) for p in broken.fragments]
    fr = settings.fracture
    rms_mirrored = template_fit_rms(bodies, template.vertices, template.faces, fr, bone=bone)
    rms_plain = template_fit_rms(bodies, plain_vertices, plain_faces, fr, bone=bone)
    log.info("proximal fragment onto the template: RMS %.2f mm mirrored, %.2f mm unmirrored", rms_mirrored,
             rms_plain)
    if rms_plain * fr.same_side_rms_ratio < rms_mirrored:
        raise InputError(f"the template seems to be the same side as the fragments (a {side} {bone}: the proximal "
                         f"fragment fits it unmirrored with RMS {rms_plain:.2f} mm, mirrored {rms_mirrored:.2f} mm); "
                         "give the other side's bone", template_path)
    if min(rms_mirrored, rms_plain) > fr.poor_rms_mm:
        raise InputError(f"the fragments do not fit the template (a {side} {bone}; the proximal fragment's RMS "
                         f"{rms_mirrored:.2f} mm mirrored, {rms_plain:.2f} mm unmirrored, beyond "
                         f"{fr.poor_rms_mm:g} mm): is it the same bone as {Path(source).name}?", template_path)
    try:
        reduction = reduce_fragments(bodies, template, fr, bone=bone)
    except BonecadError as exc:
        raise InputError(f"the fragments cannot be placed: {exc}", source) from None
    for note in reduction.notes:
        log.warning("%s", note) if "poorly" in note else log.info("%s", note)
    return Reduced(broken, reduction, bone, side)


def reduction_record(result: Reduced) -> dict:
    """reduction.json: the input, the template, per fragment its role and placement, the fracture lines."""
    reduction, broken = result.reduction, result.broken
    roles = [f.role for f in reduction.fragments]
    fragments = []
    for i, (f, piece) in enumerate(zip(reduction.fragments, broken.fragments)):
        fragments.append({
            "index": i, "role": f.role, "carries": piece.carries or None,
            "volume_mm3": round(piece.volume_mm3, 1),
            "transform": np.round(f.transform, 6).tolist(),
            "translation_mm": round(f.translation_mm, 3), "rotation_deg": round(f.rotation_deg, 3),
            "registration_rms_mm": round(f.rms_mm, 3), "periosteal_share_kept": round(f.inlier_share, 3),
            "poorly_registered": f.poor,
            "fracture_faces": int(f.fracture.sum()),
            "axial_extent_mm": [round(v, 2) for v in f.axial_extent_mm],
            "neighbours": [{"index": c.neighbour, "role": roles[c.neighbour], "overlap_mm": round(c.overlap_mm, 3),
                            "gap_mm": round(c.gap_mm, 3), "contact_share": round(c.contact_share, 3)}
                           for c in f.contacts],
        })
    template = reduction.template
    return {
        "input": broken.source,
        "bone": result.bone,
        "template": {"kind": template.kind, "source": template.source, "template_side": result.template_side,
                     "expected_uncertainty_mm": template.uncertainty_mm,
                     "expected_uncertainty_deg": template.uncertainty_deg},
        "axial_reference": "mm along the reduced bone's long axis from its distal end",
        "long_axis": np.round(reduction.up, 6).tolist(),
        "fragments": fragments,
        "fracture_lines_axial_mm": [{"lowest": round(a, 2), "highest": round(b, 2), "mean": round(m, 2)}
                                    for a, b, m in reduction.fracture_levels_mm],
        "neighbours": [{"role": p.role, "volume_mm3": round(p.volume_mm3, 1)} for p in broken.neighbours],
        "specks_dropped": list(broken.specks),
        "repairs": list(broken.repairs),
        "notes": list(reduction.notes),
    }


def run_reduce(source: str | Path, out_dir: str | Path, template_kind: str, template_path: str | Path,
               settings: Settings, *, units: Units = "auto") -> dict:
    """``bonecad reduce``: reduced.stl, reduction.json, reduction.png in ``out_dir``; returns the record."""
    return run_reduce_files(reduce_fracture(source, template_kind, template_path, settings, units=units), out_dir)


def run_reduce_files(result: Reduced, out_dir: str | Path) -> dict:
    """Write a reduction's reduced.stl, reduction.json and reduction.png into ``out_dir`` (all or nothing)."""
    import trimesh

    bodies = [FragmentBody(p.vertices, p.faces, p.role) for p in result.broken.fragments]
    reduced = result.reduction.reduced_meshes(bodies)
    record = reduction_record(result)
    source = result.broken.source
    with staged_output(out_dir) as stage:
        offsets = np.cumsum([0] + [len(v) for v, _ in reduced[:-1]])
        mesh = trimesh.Trimesh(np.concatenate([v for v, _ in reduced]),
                               np.concatenate([f + o for (_, f), o in zip(reduced, offsets)]), process=False)
        mesh.export(stage / "reduced.stl")
        (stage / "reduction.json").write_text(json.dumps(record, indent=2))
        labels = [f"{f.role}" for f in result.reduction.fragments]
        template = result.reduction.template
        reduction_png(stage / "reduction.png", [(b.vertices, b.faces) for b in bodies], reduced, labels,
                      result.reduction.up,
                      template=(apply(result.reduction.template_to_input, template.vertices), template.faces),
                      title=f"{Path(source).name} reduced onto {template.source}")
    return record


def reduced_solid(result: Reduced) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The reduced bone as one closed body: the union of the reduced fragments (manifold3d), and where a gap
    leaves them apart, the template's shape within 3 mm of the fracture lines bridging it. Returns vertices (mm),
    faces and the centres (k, 3) of the faces that are not bone surface (fracture surfaces, the bridge)."""
    import manifold3d

    def solid(vertices: np.ndarray, faces: np.ndarray):
        mesh = manifold3d.Mesh(vert_properties=np.asarray(vertices, dtype=np.float32),
                               tri_verts=np.asarray(faces, dtype=np.uint32))
        return manifold3d.Manifold(mesh).as_original()

    bodies = [FragmentBody(p.vertices, p.faces, p.role) for p in result.broken.fragments]
    reduced = result.reduction.reduced_meshes(bodies)
    parts = [solid(v, f) for v, f in reduced]
    union = manifold3d.Manifold.batch_boolean(parts, manifold3d.OpType.Add)
    if len(union.decompose()) > 1 and any(r.fracture.any() for r in result.reduction.fragments):
        template = result.reduction.template
        placed = apply(result.reduction.template_to_input, template.vertices)
        bridge = solid(placed, template.faces)
        up = result.reduction.up
        bottom = min(float((v @ up).min()) for v, _ in reduced)
        cut = np.concatenate([v[f[r.fracture]].mean(axis=1) @ up
                              for (v, f), r in zip(reduced, result.reduction.fragments) if r.fracture.any()]) - bottom
        low, high = float(cut.min()) - 3.0, float(cut.max()) + 3.0
        heights = placed @ up - bottom
        keep = np.abs(heights - 0.5 * (low + high)) < 0.5 * (high - low) + 50.0
        centre = placed[keep].mean(axis=0)
        slab = manifold3d.Manifold.cylinder(high - low, 200.0, 200.0, 64).translate(
            (0.0, 0.0, -0.5 * (high - low)))
        rot = _rotation_to(up)
        slab = slab.transform(np.column_stack([rot, centre + (bottom + 0.5 * (low + high) - centre @ up) * up]))
        union = union + (bridge ^ slab)
    mesh = union.to_mesh()
    faces = np.asarray(mesh.tri_verts, dtype=np.int64)
    vertices = np.asarray(mesh.vert_properties[:, :3], dtype=np.float64)
    origin = np.repeat(np.asarray(mesh.run_original_id), np.diff(np.asarray(mesh.run_index)) // 3)
    centres = vertices[faces].mean(axis=1)
    excluded = np.ones(len(faces), dtype=bool)  # (the bridge's faces)
    for (v, f), part, r in zip(reduced, parts, result.reduction.fragments):
        mine = origin == part.original_id()
        excluded[mine] = False
        if r.fracture.any() and mine.any():  # a face of the union on one of the fragment's fracture faces
            import igl

            on = igl.point_mesh_squared_distance(centres[mine], np.ascontiguousarray(v, dtype=np.float64),
                                                 np.ascontiguousarray(f[r.fracture], dtype=np.int64))[0]
            excluded[np.flatnonzero(mine)[on < 1e-6]] = True
    return vertices, faces, vertices[faces[excluded]].mean(axis=1)


def _rotation_to(up: np.ndarray) -> np.ndarray:
    """3 x 3 rotation taking +z to the unit ``up``."""
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(z, up), float(z @ up)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k * (1.0 / (1.0 + c))


def reconstruct_reduced(source: str | Path, out_dir: str | Path, template_kind: str, template_path: str | Path,
                        settings: Settings, *, units: Units = "auto", progress=None):
    """``bonecad reconstruct --reduce``: reduce the fragments, then model the reduced bone (the usual files in
    ``out_dir``) with the fracture surfaces and the template's bridge left out of the T-spline fit and of the
    deviation (``BoneMesh.extra["excluded_centres"]``); the reduction's own files go to ``out_dir/reduction``."""
    from dataclasses import replace

    from bonecad.mesh.intake import prepare_bone
    from bonecad.run.pipeline import reconstruct_bone

    result = reduce_fracture(source, template_kind, template_path, settings, units=units)
    vertices, faces, excluded = reduced_solid(result)
    bone = prepare_bone(vertices, faces, source=source, settings=settings.mesh, plausible=settings.units,
                        keep="femur" if result.bone == "femur" else "tibia")
    bone = replace(bone, extra={**bone.extra, "excluded_centres": excluded,
                                "excluded_mm": settings.fracture.exclusion_mm})
    settings = settings.replace("pipeline", bone=result.bone)
    reconstruction = reconstruct_bone(bone, out_dir, settings, progress=progress)
    run_reduce_files(result, Path(out_dir) / "reduction")
    return reconstruction, result
