"""The tetrahedral mesh of a STEP solid with gmsh (OpenCascade kernel): the one module that calls gmsh.

gmsh keeps one global model and writes files, so it lives at the edge, and every call here opens and
closes it (``_session``) under a lock. The STEP's faces go in as they are: the periodic B-spline tube with
its two pole caps (``tspline.step``: one face per Bezier block) and the NURBS model (``nurbs.step``) mesh as
read (measured on the phantom and the ICL tibia); a face gmsh cannot mesh raises ``InputError`` naming it.
"""
from __future__ import annotations

import logging
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path
from collections.abc import Iterator
from typing import Any

import numpy as np

from bonecad.errors import InputError
from bonecad.fe.tets import TetMesh

log = logging.getLogger(__name__)
_LOCK = threading.Lock()
#: gmsh's element types: 4-node and 10-node tetrahedra
TET4, TET10 = 4, 11


@contextmanager
def _session() -> Iterator[Any]:
    import gmsh

    with _LOCK:
        gmsh.initialize(interruptible=False)
        try:
            gmsh.option.setNumber("General.Terminal", 0)
            gmsh.option.setNumber("General.NumThreads", 1)
            gmsh.logger.start()
            yield gmsh
        finally:
            gmsh.logger.stop()
            gmsh.finalize()


def estimated_elements(volume_mm3: float, size_mm: float) -> int:
    """Tetrahedra of edge ``size_mm`` filling ``volume_mm3`` (regular tetrahedra: h^3 / (6 sqrt 2) each);
    the mesh's count is this times 1.2-2 where curvature refines it (measured: ICL tibia, phantom)."""
    return int(volume_mm3 / (size_mm ** 3 / (6.0 * np.sqrt(2.0))))


def mesh_step(step: Path, size_mm: float, order: int, *, curvature_elements: int, min_size_share: float,
              max_elements: int, netgen: bool = True) -> TetMesh:
    """Tetrahedra of the one solid in ``step``: edge length ``size_mm`` at most, down to
    ``min_size_share * size_mm`` where the surface curves (``curvature_elements`` per full turn), first or
    second order (gmsh's node order; the second-order nodes on the curved geometry), optimised by gmsh's
    own pass and, with ``netgen``, Netgen's; element quality SICN and gamma. InputError when the file
    holds no solid, gmsh fails, or the mesh would exceed ``max_elements``."""
    with _session() as gmsh:
        try:
            gmsh.model.occ.importShapes(str(step))
            gmsh.model.occ.synchronize()
        except Exception as exc:
            raise InputError(f"gmsh cannot read the model: {exc}", step) from None
        volumes = gmsh.model.getEntities(3)
        if len(volumes) != 1:
            raise InputError(f"the model holds {len(volumes)} solids, expected one closed solid", step)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size_mm)
        gmsh.option.setNumber("Mesh.MeshSizeMin", min_size_share * size_mm)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", curvature_elements)
        gmsh.option.setNumber("Mesh.Optimize", 1)
        gmsh.option.setNumber("Mesh.OptimizeNetgen", 1 if netgen else 0)
        gmsh.option.setNumber("Mesh.ElementOrder", 1)
        gmsh.option.setNumber("Mesh.HighOrderOptimize", 0)
        gmsh.option.setNumber("Mesh.Binary", 0)
        try:
            gmsh.model.mesh.generate(2)
            _check_count(gmsh, size_mm, max_elements, step)
            gmsh.model.mesh.generate(3)
            if order == 2:
                gmsh.model.mesh.setOrder(2)
        except InputError:
            raise
        except Exception as exc:
            last = [m for m in gmsh.logger.get() if "Error" in m][-3:]
            raise InputError(f"gmsh could not mesh the model at {size_mm} mm: {exc} {' '.join(last)}; try another "
                             "--size, or --model nurbs/tspline", step) from None
        types, tags, node_tags = gmsh.model.mesh.getElements(3)
        kind = TET10 if order == 2 else TET4
        if kind not in list(types):
            raise InputError(f"gmsh made no tetrahedra of the model at {size_mm} mm", step)
        k = list(types).index(kind)
        elem_tags = np.asarray(tags[k])
        if len(elem_tags) > max_elements:
            raise InputError(f"{len(elem_tags)} elements at {size_mm} mm exceed [fe] max_elements = {max_elements}: "
                             "give a larger --size or raise max_elements in --config", step)
        conn = np.asarray(node_tags[k], dtype=np.int64).reshape(len(elem_tags), -1)
        all_tags, coords, _ = gmsh.model.mesh.getNodes()
        index = np.full(int(all_tags.max()) + 1, -1, dtype=np.int64)
        used = np.unique(conn)
        index[used] = np.arange(len(used))
        position = np.full(int(all_tags.max()) + 1, -1, dtype=np.int64)
        position[all_tags.astype(np.int64)] = np.arange(len(all_tags))
        nodes = coords.reshape(-1, 3)[position[used]]
        sicn = np.asarray(gmsh.model.mesh.getElementQualities(elem_tags, "minSICN"))
        gamma = np.asarray(gmsh.model.mesh.getElementQualities(elem_tags, "gamma"))
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "bone.msh"
            gmsh.option.setNumber("Mesh.SaveAll", 0)
            gmsh.model.addPhysicalGroup(3, [volumes[0][1]], 1, "bone")
            gmsh.write(str(path))
            msh = path.read_bytes()
    log.info("gmsh: %d elements (order %d), %d nodes at %.2f mm", len(conn), order, len(nodes), size_mm)
    return TetMesh(nodes, index[conn], sicn, gamma, msh)


def _check_count(gmsh, size_mm: float, max_elements: int, step: Path) -> None:
    """InputError when the surface mesh already says the volume mesh would exceed ``max_elements``:
    the enclosed volume over a regular tetrahedron of the surface triangles' mean edge, times 1.2."""
    types, _, tri_nodes = gmsh.model.mesh.getElements(2)
    tags, coords, _ = gmsh.model.mesh.getNodes()
    pos = np.full(int(tags.max()) + 1, -1, dtype=np.int64)
    pos[tags.astype(np.int64)] = np.arange(len(tags))
    xyz = coords.reshape(-1, 3)
    corners = np.concatenate([np.asarray(t, dtype=np.int64) for k, t in zip(types, tri_nodes) if k == 2])
    tri = xyz[pos[corners.reshape(-1, 3)]]
    volume = abs(float(np.sum(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])))) / 6.0)
    edge = float(np.mean(np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1)))
    estimate = int(1.2 * estimated_elements(volume, min(edge, size_mm)))
    if estimate > max_elements:
        raise InputError(f"about {estimate} elements at {size_mm} mm would exceed [fe] max_elements = {max_elements}: "
                         "give a larger --size or raise max_elements in --config", step)
