"""bonecad fe: gmsh's tetrahedra of a STEP solid, their node order in every file, the files read back, the
solver check against beam theory on a tube, and bad input (exit 2, nothing written).

About 40 s (a tube of 4 k second-order tetrahedra, three direct solves; two CLI runs at 6 mm)."""
from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import meshio
import numpy as np
import pytest

from bonecad.errors import InputError
from bonecad.export.fe import FEDocument
from bonecad.export.registry import export
from bonecad.fe.elasticity import solve_cases, stiffness_matrix
from bonecad.fe.materials import group_moduli
from bonecad.fe.tets import GMSH_TO_VTK, VTK_EDGES, element_regions, end_node_sets
from bonecad.run.cli import main
from bonecad.run.tetmesh import mesh_step

R_OUT, R_IN, LENGTH = 10.0, 7.0, 200.0


@pytest.fixture(scope="module")
def tube_step(tmp_path_factory) -> Path:
    """A tube (outer radius 10 mm, inner 7 mm, 200 mm long along +z from z = 0) as a STEP solid."""
    from build123d import Cylinder, Pos, export_step

    path = tmp_path_factory.mktemp("tube") / "tspline.step"
    export_step(Pos(0, 0, LENGTH / 2) * (Cylinder(R_OUT, LENGTH) - Cylinder(R_IN, LENGTH)), str(path))
    return path


@pytest.fixture(scope="module")
def tube_mesh(tube_step):
    return mesh_step(tube_step, 5.0, 2, curvature_elements=12, min_size_share=0.25, max_elements=10**6)


def _frame_json(folder: Path, input_file: str = "tube.stl") -> None:
    frame = {"input": {"file": input_file},
             "bone_frame": {"origin": [0.0, 0.0, 0.0], "lateral": [1.0, 0.0, 0.0], "anterior": [0.0, 1.0, 0.0],
                            "proximal": [0.0, 0.0, 1.0]},
             "regions_mm_above_origin": {"distal": [0.0, 40.0], "shaft": [40.0, 160.0], "proximal": [160.0, 200.0]}}
    (folder / "frame.json").write_text(json.dumps(frame))


def test_gmsh_tet10_node_order_against_gmsh_reference_element():
    """gmsh's own reference 10-node tetrahedron, reordered by GMSH_TO_VTK, has nodes 4-9 at the midpoints of
    the VTK/Abaqus/FEBio edges."""
    import gmsh

    gmsh.initialize()
    try:
        _, _, _, n, local, _ = gmsh.model.mesh.getElementProperties(11)
    finally:
        gmsh.finalize()
    ref = np.asarray(local).reshape(n, 3)[GMSH_TO_VTK]
    assert np.allclose(ref[4:], ref[VTK_EDGES].mean(axis=1))
    # and the unpermuted order is not that one: the swap is needed
    assert not np.allclose(np.asarray(local).reshape(n, 3)[4:], ref[VTK_EDGES].mean(axis=1))


def test_tube_mesh_quality_and_volume(tube_mesh):
    m = tube_mesh
    assert m.order == 2 and m.tets.shape[1] == 10
    assert m.sicn.min() > 0.1 and np.all(m.volumes() > 0)
    exact = np.pi * (R_OUT ** 2 - R_IN ** 2) * LENGTH
    # straight-sided corner tetrahedra of a 12-per-turn mesh: the chords cut the circles (3 % at 30 degrees)
    assert 0.95 < m.volumes().sum() / exact < 1.0


def test_tube_stiffness_within_two_percent_of_beam_theory(tube_mesh):
    """Axial, bending and torsion stiffness of the second-order tube (end faces: one fixed, one moved as a
    plate) against beam theory on the same mesh's cross-sections; measured 0.18 %, 0.60 %, 0.03 %."""
    m = tube_mesh
    found = solve_cases(m.nodes, m.tets, np.full(len(m.tets), 10000.0), 0.3, np.zeros(3), np.array([0.0, 0.0, 1.0]),
                        0.01, ("axial", "bending", "torsion"), order=2, hollow=True)
    for case, k in found.items():
        assert abs(k.ratio - 1.0) < 0.02, (case, k)
    # beam theory itself against the analytic tube, scaled by the mesh's faceted area
    area = m.volumes().sum() / LENGTH
    assert found["axial"].beam == pytest.approx(10000.0 * area / LENGTH, rel=0.01)


def test_stiffness_matrix_equals_scikit_fem_assembly(tube_mesh):
    """The vectorised assembly gives scikit-fem's own linear-elasticity matrix (its dof numbering)."""
    from skfem import Basis, ElementTetP2, ElementVector, MeshTet, asm
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    m = tube_mesh
    keep = np.arange(0, len(m.tets), 7)
    tets = m.tets[keep]
    used, inv = np.unique(tets[:, :4], return_inverse=True)
    nodes, tets4 = m.nodes[used], inv.reshape(-1, 4)
    K, _ = stiffness_matrix(nodes, tets4, np.full(len(tets4), 1000.0), 0.3, 2)
    basis = Basis(MeshTet(nodes.T.copy(), tets4.T.copy()), ElementVector(ElementTetP2()))
    ref = asm(linear_elasticity(*lame_parameters(1000.0, 0.3)), basis)
    assert abs(K - ref).max() < 1e-9 * abs(ref).max()


def _document(mesh) -> FEDocument:
    origin, axis = np.zeros(3), np.array([0.0, 0.0, 1.0])
    regions = element_regions(mesh, origin, axis, (40.0, 160.0))
    node_sets = end_node_sets(mesh, origin, axis, 0.01)
    z = mesh.centroids()[:, 2]
    materials = group_moduli(5000.0 + 100.0 * z, mesh.volumes(), 5, 0.3)
    return FEDocument(mesh, materials, regions, node_sets, {"format": "bonecad.fe"})


def _feb(path: Path) -> dict:
    """An FEBio 4.0 reader of our own, from the format: nodes, elements per part, materials, sets."""
    root = ET.parse(path).getroot()
    assert root.tag == "febio_spec" and root.get("version") == "4.0"
    mats = {m.get("name"): (float(m.find("E").text), float(m.find("v").text)) for m in root.iter("material")}
    mesh = root.find("Mesh")
    nodes = {int(n.get("id")): [float(x) for x in n.text.split(",")] for n in mesh.find("Nodes")}
    parts = {p.get("name"): (p.get("type"), {int(e.get("id")): [int(x) for x in e.text.split(",")] for e in p})
             for p in mesh.findall("Elements")}
    node_sets = {s.get("name"): [int(x) for x in s.text.split(",")] for s in mesh.findall("NodeSet")}
    elem_sets = {s.get("name"): [int(x) for x in s.text.split(",")] for s in mesh.findall("ElementSet")}
    domains = {d.get("name"): d.get("mat") for d in root.find("MeshDomains")}
    return {"materials": mats, "nodes": nodes, "parts": parts, "node_sets": node_sets, "elem_sets": elem_sets,
            "domains": domains}


def test_files_read_back_with_the_same_nodes_elements_materials_and_sets(tube_mesh, tmp_path):
    doc = _document(tube_mesh)
    files = export("fe", doc, tmp_path)
    assert set(files) == {"inp", "feb", "msh", "vtu", "json"}
    conn = tube_mesh.vtk_order()
    for fmt in ("inp", "vtu", "msh"):
        back = meshio.read(files[fmt])
        assert np.allclose(back.points, tube_mesh.nodes, atol=1e-6), fmt
        cells = back.get_cells_type("tetra10")
        assert np.array_equal(cells, conn), fmt
    # the edge nodes sit by their own edges (curved boundary nodes move off the chord, not to another edge)
    p = tube_mesh.nodes[conn]
    mids = p[:, VTK_EDGES].mean(axis=2)  # (m, 6, 3)
    dist = np.linalg.norm(p[:, 4:, None, :] - mids[:, None, :, :], axis=3)  # node k vs every edge midpoint
    assert np.all(np.argmin(dist, axis=2) == np.arange(6))
    feb = _feb(files["feb"])
    assert len(feb["nodes"]) == len(tube_mesh.nodes)
    elems = {}
    for name, (kind, part) in feb["parts"].items():
        assert kind == "tet10" and feb["domains"][name] == name
        e_mpa, nu = feb["materials"][name]
        k = int(name.split("_")[1]) - 1
        assert e_mpa == pytest.approx(doc.materials.moduli_mpa[k], rel=1e-5) and nu == 0.3
        assert sorted(part) == sorted(np.flatnonzero(doc.materials.element_material == k) + 1)
        elems.update(part)
    assert len(elems) == len(conn) and all(elems[i + 1] == list(conn[i] + 1) for i in range(0, len(conn), 97))
    for name, idx in doc.regions.items():
        assert feb["elem_sets"][name] == list(idx + 1)
    for name, idx in doc.node_sets.items():
        assert feb["node_sets"][name] == list(idx + 1)
    inp = files["inp"].read_text()
    assert inp.count("*Material,") == len(doc.materials.moduli_mpa) and "*Nset, nset=DISTAL_END" in inp
    assert "*Elset, elset=PROXIMAL" in inp and "type=C3D10" in inp


def test_fe_command_on_a_reconstruction_folder(tube_step, tmp_path):
    folder = tmp_path / "recon"
    folder.mkdir()
    (folder / "tspline.step").write_bytes(tube_step.read_bytes())
    _frame_json(folder)
    out = tmp_path / "fe"
    assert main(["fe", str(folder), "--out", str(out), "--size", "6", "-q"]) == 0
    assert {p.name for p in out.iterdir()} == {"bone.msh", "bone.vtu", "bone.inp", "bone.feb", "fe.json"}
    doc = json.loads((out / "fe.json").read_text())
    assert doc["materials"]["source"] == "homogeneous" and doc["quality"]["sicn"]["min"] > 0.1
    assert abs(doc["volume_mm3"]["relative_difference"]) < 0.05
    assert set(doc["stiffness"]) == {"axial", "torsion"}


def test_bad_input_exits_2_and_writes_nothing(tube_step, tmp_path, capsys):
    from bonecad.imaging.volume import CTVolume, write_nifti

    folder = tmp_path / "recon"
    folder.mkdir()
    (folder / "tspline.step").write_bytes(tube_step.read_bytes())
    ct = tmp_path / "ct.nii.gz"
    write_nifti(CTVolume(np.full((4, 4, 4), -1000.0, dtype=np.float32), np.eye(4)), ct)
    _frame_json(folder, str(ct))
    out = tmp_path / "fe"
    # a CT input without the scanner's calibration
    assert main(["fe", str(folder), "--out", str(out), "-q"]) == 2
    assert "--calibration" in capsys.readouterr().err and not out.exists()
    # too many elements for [fe] max_elements
    config = tmp_path / "small.toml"
    config.write_text("[fe]\nmax_elements = 1000\n")
    assert main(["fe", str(folder), "--out", str(out), "--homogeneous", "--config", str(config), "-q"]) == 2
    assert "max_elements" in capsys.readouterr().err and not out.exists()
    # a model that is no solid
    from build123d import Rectangle, export_step

    export_step(Rectangle(10, 10).faces()[0], str(folder / "nurbs.step"))
    assert main(["fe", str(folder), "--model", "nurbs", "--out", str(out), "--homogeneous", "-q"]) == 2
    assert "solid" in capsys.readouterr().err and not out.exists()
    assert not list(tmp_path.glob(".fe.staging*"))


def test_mesh_step_refuses_a_file_without_solid(tmp_path):
    path = tmp_path / "empty.step"
    path.write_text("not a step file")
    with pytest.raises(InputError):
        mesh_step(path, 5.0, 1, curvature_elements=12, min_size_share=0.25, max_elements=1000)


@pytest.mark.slow
def test_fe_on_the_demo_ct_maps_moduli_from_the_ct(demo_run, tmp_path):
    """The demo's reconstruction came from its CT: with a calibration the moduli come from it, grouped; the
    T-spline's solid meshes at 2 mm with SICN above 0.1 and the volume within 0.5 % of the B-rep's (at 4 mm:
    0.59 % below it)."""
    out = tmp_path / "fe"
    assert main(["fe", str(demo_run), "--out", str(out), "--size", "2", "--calibration", "0.0008", "0", "--iga",
                 "-q"]) == 0
    doc = json.loads((out / "fe.json").read_text())
    mats = doc["materials"]
    assert mats["source"] == "ct" and 1 < mats["count"] <= 100 and mats["max_grouping_error"] < 0.1
    assert doc["quality"]["sicn"]["min"] > 0.1
    assert abs(doc["volume_mm3"]["relative_difference"]) < 0.005
    assert (out / "tspline.iga").exists()
    vtu = meshio.read(out / "bone.vtu")
    e = vtu.cell_data["element_modulus_mpa"][0]
    assert e.min() >= 1.0 and e.max() < 30000.0 and np.ptp(e) > 1000.0
