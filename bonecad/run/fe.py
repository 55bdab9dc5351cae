"""``bonecad fe``: a reconstruction's solid -> tetrahedral mesh, CT-based stiffness, solver check, files.

SOURCE is a ``reconstruct`` output folder (its tspline.step or nurbs.step and frame.json), or a mesh file
or CT volume, which is reconstructed first (in-process, into a temporary folder). The moduli come from the
CT when the input was one (frame.json names it) or ``--ct`` gives one, and the calibration is known
(``[fe] hu_to_density``); otherwise every element gets ``[fe] cortical_modulus_mpa`` and fe.json says so.
"""
from __future__ import annotations

import json
import logging
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bonecad.errors import InputError, KernelError
from bonecad.export.fe import FEDocument
from bonecad.export.registry import export
from bonecad.fe.elasticity import solve_cases
from bonecad.fe.materials import (Calibration, element_moduli, group_moduli, sample_trilinear,
                                  subdivision_levels)
from bonecad.fe.tets import TetMesh, element_regions, end_node_sets, quality_summary
from bonecad.settings import FESettings, Settings
from bonecad.staging import staged_output

log = logging.getLogger(__name__)


def _folder_model(folder: Path, model: str) -> tuple[Path, dict]:
    step = folder / f"{model}.step"
    try:
        frame = json.loads((folder / "frame.json").read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"not a bonecad reconstruction folder (frame.json): {exc}", folder) from None
    if not step.exists():
        raise InputError(f"no {step.name} in this reconstruction folder: run `bonecad reconstruct` with --model "
                         f"{model} or both, or give --model {'nurbs' if model == 'tspline' else 'tspline'}", folder)
    return step, frame


def calibration_of(fe: FESettings, source: Path) -> Calibration:
    """The HU -> modulus chain of the settings; InputError when the scanner's calibration is not given."""
    if len(fe.hu_to_density) != 2:
        raise InputError("CT-based stiffness needs the scanner's calibration, rho (g/cm3) = slope * HU + intercept "
                         "from a density phantom scanned with the bone: give --calibration SLOPE INTERCEPT (or "
                         "[fe] hu_to_density = [slope, intercept] in --config), or --homogeneous for one cortical "
                         "modulus", source)
    slope, intercept = fe.hu_to_density
    return Calibration(slope, intercept, fe.ash_from_qct, fe.ash_share_of_apparent, fe.modulus_law,
                       fe.modulus_density, fe.min_modulus_mpa)


def ct_moduli(mesh: TetMesh, ct_path: Path, fe: FESettings) -> tuple[np.ndarray, dict[str, Any]]:
    """(m,) element moduli (MPa) from the CT, and what was done (levels, voxel, calibration)."""
    from bonecad.imaging.volume import read_volume

    calibration = calibration_of(fe, ct_path)
    volume = read_volume(ct_path)
    voxel = float(np.min(volume.spacing_mm))
    levels = subdivision_levels(mesh.nodes, mesh.tets, voxel, fe.quadrature_voxels)
    hu = np.asarray(volume.hu, dtype=np.float64)
    inside = volume.world_to_index(mesh.nodes)
    if np.any(inside < -0.5) or np.any(inside > np.array(hu.shape[::-1]) - 0.5):
        raise InputError("the mesh reaches outside the CT volume: is this the bone's own scan?", ct_path)

    def modulus_at(points: np.ndarray) -> np.ndarray:
        return calibration.modulus(sample_trilinear(hu, volume.world_to_index, points, float(hu.min())))

    moduli = element_moduli(mesh.nodes, mesh.tets, modulus_at, levels)
    info = {"ct": str(ct_path), "voxel_mm": [round(float(v), 4) for v in volume.spacing_mm],
            "quadrature": f"4-point rule on 8^{levels} sub-tetrahedra per element (trilinear CT)",
            "hu_to_density": list(fe.hu_to_density), "ash_from_qct": list(fe.ash_from_qct),
            "ash_share_of_apparent": fe.ash_share_of_apparent,
            "modulus_law": f"E = {fe.modulus_law[0]} * rho_{fe.modulus_density} ^ {fe.modulus_law[1]} MPa"}
    return moduli, info


def run_fe(source: str | Path, out_dir: str | Path, settings: Settings, *, model: str = "tspline",
           ct: Path | None = None, homogeneous: bool = False, iga: bool = False, units: str = "auto") -> FEDocument:
    """``bonecad fe``; returns the document written (fe.json's ``summary``)."""
    source = Path(source)
    fe = settings.fe
    timings: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="bonecad-fe-") as tmp:
        if source.is_dir() and (source / "frame.json").exists():
            folder = source
        else:
            from bonecad.run.pipeline import reconstruct

            start = time.perf_counter()
            models = settings.replace("pipeline", models=[model])
            reconstruct(source, Path(tmp), models, until="models", units=units)  # type: ignore[arg-type]
            folder = Path(tmp)
            timings["reconstruct_s"] = time.perf_counter() - start
        step, frame = _folder_model(folder, model)
        doc = build_fe(step, frame, fe, ct=ct, homogeneous=homogeneous, timings=timings)
        with staged_output(Path(out_dir)) as stage:
            export("fe", doc, stage)
            if iga:
                from bonecad.export.iga import iga_from_json

                if not (folder / "tspline.json").exists():
                    raise InputError("--iga needs the T-spline model (tspline.json): reconstruct with --model "
                                     "tspline or both", folder)
                iga_from_json(folder / "tspline.json", stage)
    return doc


def build_fe(step: Path, frame: dict, fe: FESettings, *, ct: Path | None = None, homogeneous: bool = False,
             timings: dict[str, float] | None = None) -> FEDocument:
    """The FE document of one STEP solid and its reconstruction's frame.json."""
    from bonecad.occ.brep import volume_mm3
    from bonecad.occ.exchange import read_named_step
    from bonecad.run.pipeline import is_volume
    from bonecad.run.tetmesh import mesh_step

    timings = dict(timings or {})
    bone_frame = frame["bone_frame"]
    origin = np.array(bone_frame["origin"], dtype=np.float64)
    axis = np.array(bone_frame["proximal"], dtype=np.float64)
    axis /= np.linalg.norm(axis)
    regions_mm = frame["regions_mm_above_origin"]
    bounds = (float(regions_mm["distal"][1]), float(regions_mm["proximal"][0]))
    ct_path = ct
    if ct_path is None and not homogeneous:
        given = Path(frame.get("input", {}).get("file", ""))
        if str(given) and is_volume(given) and given.exists():
            ct_path = given
    if ct_path is not None and not homogeneous:
        calibration_of(fe, ct_path)  # a missing calibration fails before the meshing
    try:
        solid, _ = read_named_step(step)
    except KernelError as exc:
        raise InputError(str(exc), step) from None
    brep_volume = volume_mm3(solid)
    start = time.perf_counter()
    mesh = mesh_step(step, fe.size_mm, fe.order, curvature_elements=fe.curvature_elements,
                     min_size_share=fe.min_size_share, max_elements=fe.max_elements, netgen=fe.netgen)
    timings["mesh_s"] = time.perf_counter() - start
    volumes = mesh.volumes()
    if np.any(volumes <= 0):
        raise KernelError(f"{int(np.sum(volumes <= 0))} inverted elements in the mesh of {step}")
    regions = element_regions(mesh, origin, axis, bounds)
    node_sets = end_node_sets(mesh, origin, axis, fe.end_depth_mm)
    start = time.perf_counter()
    if ct_path is not None and not homogeneous:
        moduli, material_info = ct_moduli(mesh, ct_path, fe)
        materials = group_moduli(moduli, volumes, fe.materials, fe.poisson, "ct")
    else:
        moduli = np.full(len(mesh.tets), fe.cortical_modulus_mpa)
        materials = group_moduli(moduli, volumes, 1, fe.poisson, "homogeneous")
        material_info = {"note": "no CT: one homogeneous modulus, [fe] cortical_modulus_mpa, for the whole bone "
                                 "(a solid bone of cortical stiffness: no marrow, no trabecular bone)"}
    timings["materials_s"] = time.perf_counter() - start
    stiffness = {}
    if fe.solver_check:
        start = time.perf_counter()
        found = solve_cases(mesh.nodes, mesh.tets, materials.moduli_mpa[materials.element_material], fe.poisson,
                            origin, axis, fe.end_depth_mm, ("axial", "torsion"), order=1)
        timings["solve_s"] = time.perf_counter() - start
        for case, k in found.items():
            unit = "N/mm" if case == "axial" else "N mm/rad"
            stiffness[case] = {"solver": round(k.solver, 1), "beam_theory": round(k.beam, 1),
                               "ratio": round(k.ratio, 4), "unit": unit, "dofs": k.dofs, "iterations": k.iterations}
    mesh_volume = float(volumes.sum())
    summary = {
        "format": "bonecad.fe", "model": step.name, "size_mm": fe.size_mm, "order": mesh.order,
        "elements": len(mesh.tets), "nodes": len(mesh.nodes),
        "quality": {"sicn": quality_summary(mesh.sicn), "gamma": quality_summary(mesh.gamma)},
        "volume_mm3": {"mesh": round(mesh_volume, 1), "brep": round(brep_volume, 1),
                       "relative_difference": round(mesh_volume / brep_volume - 1.0, 6),
                       "note": "straight-sided tetrahedra (the corner nodes)"},
        "regions": {name: {"elements": len(idx)} for name, idx in regions.items()},
        "region_bounds_mm_above_origin": list(bounds),
        "node_sets": {name: len(idx) for name, idx in node_sets.items()},
        "end_depth_mm": fe.end_depth_mm,
        "materials": {"source": materials.source, "count": len(materials.moduli_mpa),
                      "moduli_mpa": [round(float(e), 1) for e in materials.moduli_mpa],
                      "poisson": fe.poisson, "max_grouping_error": round(materials.max_grouping_error, 4),
                      **material_info},
        "stiffness": stiffness,
        "load_cases": "distal end's nodes fixed; proximal end's nodes moved as one rigid plate along the axis "
                      "(axial) or about it (torsion); linear tetrahedra on the corner nodes (order 1 fields, also for "
                      "a second-order mesh); beam theory from the mesh's cross-sections between the two",
        "frame": {"origin": origin.tolist(), "long_axis": axis.tolist()},
        "timings_s": {k: round(v, 2) for k, v in timings.items()},
        "note_timings": "wall-clock seconds, one process",
    }
    return FEDocument(mesh, materials, regions, node_sets, summary)


def fe_settings(settings: Settings, size_mm: float | None, order: int | None,
                calibration: tuple[float, float] | None) -> Settings:
    """The settings with ``--size``, ``--order`` and ``--calibration`` laid over ``[fe]``."""
    values: dict[str, Any] = {}
    if size_mm is not None:
        values["size_mm"] = size_mm
    if order is not None:
        values["order"] = order
    if calibration is not None:
        values["hu_to_density"] = list(calibration)
    return settings.replace("fe", **values) if values else settings

