"""CT -> element moduli: the quadrature, the calibration chain, and the mapped moduli against the exact
element integrals of a known density field (a few seconds)."""
from __future__ import annotations

import numpy as np
import pytest

from bonecad.fe.materials import (Calibration, element_moduli, group_moduli, quadrature, sample_trilinear,
                                  subdivision_levels)
from bonecad.fe.tets import tet_volumes
from bonecad.imaging.volume import CTVolume
from bonecad.settings import Settings

FE = Settings.load().fe
CAL = Calibration(0.0008, 0.0, FE.ash_from_qct, FE.ash_share_of_apparent, FE.modulus_law, FE.modulus_density,
                  FE.min_modulus_mpa)


def _hu(p: np.ndarray) -> np.ndarray:
    """The known field: a smooth shell of cortical HU (1600) round a trabecular core (200), varying over
    millimetres, as a bone's cortex does."""
    r = np.hypot(p[..., 0] - 1.0, p[..., 1] + 0.5)
    return 200.0 + 1400.0 / (1.0 + np.exp(-(r - 8.0) / 1.2)) + 80.0 * np.sin(p[..., 2] / 3.0)


@pytest.mark.parametrize("levels", [0, 1, 2])
def test_quadrature_integrates_quadratics_exactly(levels):
    bary, w = quadrature(levels)
    assert w.sum() == pytest.approx(1.0) and np.all(bary >= 0) and np.allclose(bary.sum(axis=1), 1.0)
    # mean of l_i l_j over the tetrahedron: (1 + delta_ij) / 20
    m = np.einsum("q,qi,qj->ij", w, bary, bary)
    assert np.allclose(m, (1.0 + np.eye(4)) / 20.0)


def test_calibration_chain():
    # 1000 HU -> 0.8 g/cm3 QCT -> ash 0.7806 -> Keller 10500 * 0.7806^2.57
    assert CAL.modulus(np.array([1000.0]))[0] == pytest.approx(10500 * (0.877 * 0.8 + 0.079) ** 2.57)
    assert CAL.modulus(np.array([-1000.0]))[0] == FE.min_modulus_mpa


def test_mapped_moduli_within_two_percent_of_exact_element_integrals():
    """A CT of 0.5 mm voxels sampled from the known field; tetrahedra of about 2 mm: each element's modulus
    against the integral of E(HU(x)) of the field itself (a fine quadrature of the exact field)."""
    rng = np.random.default_rng(3)
    voxel = 0.5
    n = (70, 60, 60)  # k, j, i
    affine = np.diag([voxel, voxel, voxel, 1.0])
    affine[:3, 3] = [-15.0, -15.0, -15.0]
    k, j, i = np.meshgrid(*[np.arange(m) for m in n], indexing="ij")
    world = np.stack([i, j, k], axis=-1) * voxel + affine[:3, 3]
    ct = CTVolume(_hu(world).astype(np.float32), affine)
    # random tetrahedra of about 2 mm inside the volume
    centres = rng.uniform(-10.0, 10.0, size=(300, 3))
    nodes = (centres[:, None, :] + rng.normal(scale=1.2, size=(300, 4, 3))).reshape(-1, 3)
    tets = np.arange(len(nodes)).reshape(-1, 4)
    flip = tet_volumes(nodes, tets) < 0
    tets[flip] = tets[flip][:, [1, 0, 2, 3]]
    hu = ct.hu.astype(np.float64)
    levels = subdivision_levels(nodes, tets, voxel, FE.quadrature_voxels)
    mapped = element_moduli(nodes, tets, lambda p: CAL.modulus(sample_trilinear(hu, ct.world_to_index, p, -1000.0)),
                            levels)
    exact = element_moduli(nodes, tets, lambda p: CAL.modulus(_hu(p)), 4)
    centre = CAL.modulus(_hu(nodes[tets].mean(axis=1)))
    error = np.abs(mapped / exact - 1.0)
    assert error.max() < 0.02, (levels, error.max())
    # sampling at the centre only is worse by far
    assert np.abs(centre / exact - 1.0).max() > 3 * error.max()


def test_grouping_keeps_each_modulus_within_its_bin():
    rng = np.random.default_rng(0)
    e = np.exp(rng.uniform(np.log(5.0), np.log(20000.0), 5000))
    mats = group_moduli(e, np.ones_like(e), 100, 0.3)
    assert len(mats.moduli_mpa) <= 100
    step = np.exp((np.log(e.max()) - np.log(e.min())) / 100) - 1.0
    assert mats.max_grouping_error <= step
    assert np.allclose(mats.moduli_mpa[mats.element_material] / e, 1.0, atol=step)
