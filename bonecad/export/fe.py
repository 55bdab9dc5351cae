"""The finite-element files of ``bonecad fe``: bone.msh (gmsh), bone.vtu (meshio), Abaqus bone.inp and
FEBio bone.feb (format 4.0), both written here (meshio's Abaqus writer drops materials and sets; it has no
FEBio writer), and fe.json.

Node and element numbers start at 1 in .inp and .feb; elements keep the order of the mesh, with nodes in
the VTK / Abaqus / FEBio order (``fe.tets.GMSH_TO_VTK``). Sets: element sets per region (DISTAL, SHAFT,
PROXIMAL) and per material (MAT_k), node sets of the two ends (DISTAL_END, PROXIMAL_END).
"""
from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bonecad.export.registry import exporter
from bonecad.fe.materials import Materials
from bonecad.fe.tets import TetMesh


@dataclass(frozen=True)
class FEDocument:
    """What ``bonecad fe`` writes: the mesh, its materials, element sets per region, node sets of the
    ends, and the summary (fe.json)."""

    mesh: TetMesh
    materials: Materials
    regions: dict[str, np.ndarray]
    node_sets: dict[str, np.ndarray]
    summary: dict[str, Any]


def _lines(values: np.ndarray, per_line: int = 16) -> str:
    """Integers, comma-separated, ``per_line`` to a line (Abaqus reads at most 16 per data line)."""
    v = np.asarray(values, dtype=np.int64)
    return "\n".join(", ".join(map(str, v[i:i + per_line])) for i in range(0, len(v), per_line))


def _material_sets(doc: FEDocument) -> list[tuple[str, np.ndarray, float]]:
    mats = doc.materials
    return [(f"MAT_{k + 1}", np.flatnonzero(mats.element_material == k), float(e))
            for k, e in enumerate(mats.moduli_mpa)]


@exporter("fe", "inp")
def write_inp(doc: FEDocument, out_dir: Path) -> Path:
    """bone.inp: Abaqus input (mm, N, MPa): nodes, C3D4/C3D10 elements, sets, one section and material per
    modulus group."""
    mesh = doc.mesh
    kind = "C3D10" if mesh.order == 2 else "C3D4"
    conn = mesh.vtk_order() + 1
    out = ["*Heading", f"** bonecad fe: {len(conn)} {kind} elements, units mm N MPa; "
           f"moduli: {doc.materials.source}", "*Node"]
    ids = np.arange(1, len(mesh.nodes) + 1)
    out += [f"{i}, {x:.9g}, {y:.9g}, {z:.9g}" for i, (x, y, z) in zip(ids, mesh.nodes)]
    out.append(f"*Element, type={kind}, elset=BONE")
    out += [", ".join(map(str, (e, *row))) for e, row in zip(range(1, len(conn) + 1), conn)]
    for name, elems in doc.regions.items():
        out += [f"*Elset, elset={name.upper()}", _lines(elems + 1)]
    for name, nodes in doc.node_sets.items():
        out += [f"*Nset, nset={name.upper()}", _lines(nodes + 1)]
    for name, elems, _ in _material_sets(doc):
        out += [f"*Elset, elset={name}", _lines(elems + 1)]
    for name, _, _ in _material_sets(doc):
        out += [f"*Solid Section, elset={name}, material={name}", ","]
    for name, _, e in _material_sets(doc):
        out += [f"*Material, name={name}", "*Elastic", f"{e:.6g}, {doc.materials.poisson:.6g}"]
    path = out_dir / "bone.inp"
    path.write_text("\n".join(s for s in out if s) + "\n")
    return path


@exporter("fe", "feb")
def write_feb(doc: FEDocument, out_dir: Path) -> Path:
    """bone.feb: FEBio input, format 4.0: one isotropic elastic material and one solid domain (Elements
    part) per modulus group, element sets per region, node sets of the ends."""
    mesh = doc.mesh
    kind = "tet10" if mesh.order == 2 else "tet4"
    conn = mesh.vtk_order() + 1
    root = ET.Element("febio_spec", version="4.0")
    ET.SubElement(root, "Module", type="solid")
    materials = ET.SubElement(root, "Material")
    sets = _material_sets(doc)
    for k, (name, _, e) in enumerate(sets):
        m = ET.SubElement(materials, "material", id=str(k + 1), name=name, type="isotropic elastic")
        ET.SubElement(m, "density").text = "1"
        ET.SubElement(m, "E").text = f"{e:.6g}"
        ET.SubElement(m, "v").text = f"{doc.materials.poisson:.6g}"
    m_el = ET.SubElement(root, "Mesh")
    nodes = ET.SubElement(m_el, "Nodes", name="bone")
    for i, (x, y, z) in enumerate(mesh.nodes, start=1):
        ET.SubElement(nodes, "node", id=str(i)).text = f"{x:.9g},{y:.9g},{z:.9g}"
    for name, elems, _ in sets:
        part = ET.SubElement(m_el, "Elements", type=kind, name=name)
        for e in elems:
            ET.SubElement(part, "elem", id=str(e + 1)).text = ",".join(map(str, conn[e]))
    for name, idx in doc.node_sets.items():
        ET.SubElement(m_el, "NodeSet", name=name).text = ",".join(map(str, np.asarray(idx) + 1))
    for name, idx in doc.regions.items():
        ET.SubElement(m_el, "ElementSet", name=name).text = ",".join(map(str, np.asarray(idx) + 1))
    domains = ET.SubElement(root, "MeshDomains")
    for name, _, _ in sets:
        ET.SubElement(domains, "SolidDomain", name=name, mat=name)
    ET.indent(root, space=" ")
    path = out_dir / "bone.feb"
    ET.ElementTree(root).write(path, encoding="ISO-8859-1", xml_declaration=True)
    return path


@exporter("fe", "msh")
def write_msh(doc: FEDocument, out_dir: Path) -> Path:
    """bone.msh: gmsh's own file of the mesh (format 4.1, gmsh's node order)."""
    path = out_dir / "bone.msh"
    path.write_bytes(doc.mesh.msh)
    return path


@exporter("fe", "vtu")
def write_vtu(doc: FEDocument, out_dir: Path) -> Path:
    """bone.vtu (meshio): the mesh with cell data: modulus (MPa, before and after grouping), material,
    region (0 distal, 1 shaft, 2 proximal), SICN and gamma."""
    import meshio

    mesh = doc.mesh
    region = np.full(len(mesh.tets), -1, dtype=np.int32)
    for k, name in enumerate(("distal", "shaft", "proximal")):
        region[doc.regions[name]] = k
    mats = doc.materials
    data = {"modulus_mpa": [mats.moduli_mpa[mats.element_material]], "element_modulus_mpa": [mats.element_modulus_mpa],
            "material": [mats.element_material.astype(np.int32) + 1], "region": [region],
            "sicn": [mesh.sicn], "gamma": [mesh.gamma]}
    cells = [("tetra10" if mesh.order == 2 else "tetra", mesh.vtk_order())]
    path = out_dir / "bone.vtu"
    meshio.write(path, meshio.Mesh(mesh.nodes, cells, cell_data=data), file_format="vtu")
    return path


@exporter("fe", "json")
def write_fe_json(doc: FEDocument, out_dir: Path) -> Path:
    """fe.json: the summary (mesh, quality, volumes, materials, stiffness, files)."""
    path = out_dir / "fe.json"
    path.write_text(json.dumps(doc.summary, indent=2) + "\n")
    return path
