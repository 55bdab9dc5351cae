"""CT volume readers and writers: geometry (LPS world), DICOM series handling, bad input."""
from __future__ import annotations

import nibabel as nib
import numpy as np
import pydicom
import pytest
import SimpleITK as sitk
from pydicom.uid import generate_uid

from bonecad.errors import InputError
from bonecad.imaging.volume import RAS_TO_LPS, CTVolume, read_volume, write_dicom_series, write_nifti


def _rotation(angles_deg) -> np.ndarray:
    a, b, c = np.radians(angles_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return rz @ ry @ rx


def _volume(shape=(9, 14, 17), angles=(10.0, -5.0, 30.0), spacing=(0.7, 0.8, 1.25), seed=0) -> CTVolume:
    """Integer HU (exact through int16 files), an oblique grid off the origin."""
    rng = np.random.default_rng(seed)
    hu = rng.integers(-1000, 2000, size=shape).astype(np.float32)
    affine = np.eye(4)
    affine[:3, :3] = _rotation(angles) * np.asarray(spacing)
    affine[:3, 3] = [-41.5, 23.25, 812.0]
    return CTVolume(hu=hu, affine=affine)


def test_nifti_round_trip_keeps_the_lps_world(tmp_path):
    volume = _volume()
    path = write_nifti(volume, tmp_path / "ct.nii.gz")
    back = read_volume(path)
    np.testing.assert_array_equal(back.hu, volume.hu)
    np.testing.assert_allclose(back.affine, volume.affine, atol=1e-5)
    # The file holds RAS: x and y negated against bonecad's LPS.
    np.testing.assert_allclose(nib.load(str(path)).affine, RAS_TO_LPS @ volume.affine, atol=1e-5)
    # ITK (LPS internally, its own NIfTI conversion) agrees on where voxel 0 and the axes are.
    image = sitk.ReadImage(str(path))
    np.testing.assert_allclose(image.GetOrigin(), volume.affine[:3, 3], atol=1e-4)
    direction = np.asarray(image.GetDirection()).reshape(3, 3)
    np.testing.assert_allclose(direction * image.GetSpacing(), volume.affine[:3, :3], atol=1e-5)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(image), volume.hu)


def test_dicom_round_trip_sorts_slices_by_position(tmp_path):
    volume = _volume()
    folder = write_dicom_series(volume, tmp_path / "series")
    files = sorted(folder.iterdir())
    assert len(files) == volume.shape[0]
    # Shuffle the file names: order must come from ImagePositionPatient, not names.
    rng = np.random.default_rng(1)
    for n, f in enumerate(files):
        f.rename(folder / f"tmp{n}")
    for n, f in zip(rng.permutation(len(files)), sorted(folder.iterdir())):
        f.rename(folder / f"IM{n:04d}")
    back = read_volume(folder)
    np.testing.assert_array_equal(back.hu, volume.hu)
    np.testing.assert_allclose(back.affine, volume.affine, atol=1e-5)
    ds = pydicom.dcmread(next(folder.iterdir()))
    assert ds.Modality == "CT" and float(ds.RescaleIntercept) == -1024.0 and float(ds.RescaleSlope) == 1.0
    # ITK's DICOM reader sees the same geometry.
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(reader.GetGDCMSeriesFileNames(str(folder)))
    image = reader.Execute()
    np.testing.assert_allclose(image.GetOrigin(), volume.affine[:3, 3], atol=1e-4)
    np.testing.assert_allclose(sitk.GetArrayFromImage(image), volume.hu)


def test_one_dicom_file_reads_its_series(tmp_path):
    volume = _volume()
    folder = write_dicom_series(volume, tmp_path / "series")
    back = read_volume(sorted(folder.iterdir())[5])
    np.testing.assert_array_equal(back.hu, volume.hu)
    assert back.source == str(folder)


def test_writers_give_the_same_files_for_the_same_volume_and_new_uids_for_another(tmp_path):
    volume = _volume()
    first = write_dicom_series(volume, tmp_path / "first")
    again = write_dicom_series(volume, tmp_path / "again")
    for a in sorted(first.iterdir()):
        assert a.read_bytes() == (again / a.name).read_bytes(), a.name
    uids = [pydicom.dcmread(f).SOPInstanceUID for f in sorted(first.iterdir())]
    assert len(set(uids)) == len(uids)
    other = _volume(seed=7)
    series = {pydicom.dcmread(next(write_dicom_series(v, tmp_path / n).iterdir())).SeriesInstanceUID
              for v, n in ((volume, "a"), (other, "b"))}
    assert len(series) == 2
    nifti = write_nifti(volume, tmp_path / "a.nii.gz").read_bytes()
    assert nifti[4:8] == b"\0\0\0\0"  # no gzip time stamp (whole seconds: two writes in a second would match anyway)
    assert nifti == write_nifti(volume, tmp_path / "b.nii.gz").read_bytes()


def test_dicom_folder_picks_the_ct_series_with_most_slices(tmp_path):
    folder = tmp_path / "study"
    write_dicom_series(_volume(shape=(5, 14, 17), seed=1), folder / "a")
    big = _volume(shape=(8, 14, 17), seed=2)
    write_dicom_series(big, folder / "b")
    mr = folder / "c"
    write_dicom_series(_volume(shape=(12, 14, 17), seed=3), mr)
    for f in mr.iterdir():
        ds = pydicom.dcmread(f)
        ds.Modality = "MR"
        ds.save_as(f)
    (folder / "README.txt").write_text("not an image")
    back = read_volume(folder)
    np.testing.assert_array_equal(back.hu, big.hu)


def test_missing_slices_are_resampled_onto_the_regular_grid(tmp_path):
    volume = _volume(shape=(12, 10, 11), angles=(0.0, 0.0, 0.0))
    hu = volume.hu.copy()
    for k in (3, 7, 8):  # what the phantom does: interpolate the missing slices
        hu[k] = np.nan
    for k, (lo, hi) in {3: (2, 4), 7: (6, 9), 8: (6, 9)}.items():
        w = (k - lo) / (hi - lo)
        hu[k] = volume.hu[lo] * (1 - w) + volume.hu[hi] * w
    gappy = CTVolume(hu=hu, affine=volume.affine, missing_slices=(3, 7, 8))
    folder = write_dicom_series(gappy, tmp_path / "gappy")
    assert len(list(folder.iterdir())) == 9
    back = read_volume(folder)
    assert back.shape == volume.shape
    assert back.missing_slices == (3, 7, 8)
    np.testing.assert_allclose(back.hu, hu, atol=1.0)  # stored HU are rounded to integers
    np.testing.assert_allclose(back.affine, volume.affine, atol=1e-5)


def test_a_gap_wider_than_allowed_is_refused_naming_the_slice(tmp_path):
    volume = _volume(shape=(12, 10, 11), spacing=(0.7, 0.8, 1.25))
    folder = write_dicom_series(CTVolume(volume.hu, volume.affine, missing_slices=(4, 5, 6, 7)), tmp_path / "g")
    with pytest.raises(InputError, match="gap of 6.25 mm") as info:
        read_volume(folder)
    assert pydicom.dcmread(info.value.path).InstanceNumber == 4  # the slice before the gap


def test_gantry_tilt_is_kept_as_a_sheared_grid(tmp_path):
    volume = _volume(angles=(0.0, 0.0, 0.0))
    affine = volume.affine.copy()
    tilt = np.radians(15.0)
    affine[:3, 2] = np.array([0.0, np.sin(tilt), np.cos(tilt)]) * 1.25 / np.cos(tilt)
    tilted = CTVolume(volume.hu, affine)
    back = read_volume(write_dicom_series(tilted, tmp_path / "tilted"))
    np.testing.assert_allclose(back.affine, affine, atol=1e-5)
    np.testing.assert_array_equal(back.hu, volume.hu)
    # The NIfTI sform keeps the shear too.
    np.testing.assert_allclose(read_volume(write_nifti(tilted, tmp_path / "t.nii")).affine, affine, atol=1e-5)


@pytest.mark.parametrize("suffix", [".nrrd", ".mha"])
def test_itk_formats_read_in_lps(tmp_path, suffix):
    volume = _volume()
    image = sitk.GetImageFromArray(volume.hu.astype(np.int16))
    spacing = volume.spacing_mm
    image.SetSpacing(spacing.tolist())
    image.SetDirection((volume.affine[:3, :3] / spacing).ravel().tolist())
    image.SetOrigin(volume.affine[:3, 3].tolist())
    path = tmp_path / f"ct{suffix}"
    sitk.WriteImage(image, str(path))
    back = read_volume(path)
    np.testing.assert_array_equal(back.hu, volume.hu)
    np.testing.assert_allclose(back.affine, volume.affine, atol=1e-5)


def _non_ct_nifti(tmp_path):
    path = tmp_path / "mri.nii.gz"
    data = np.random.default_rng(0).integers(0, 255, size=(10, 10, 10)).astype(np.int16)
    nib.save(nib.Nifti1Image(data, np.eye(4)), str(path))
    return path, path, "not a CT image"


def _flat_nifti(tmp_path):
    path = tmp_path / "slice.nii"
    nib.save(nib.Nifti1Image(np.zeros((10, 10, 1), dtype=np.int16), np.eye(4)), str(path))
    return path, path, "expected a 3-D image"


def _empty_folder(tmp_path):
    (tmp_path / "empty").mkdir()
    return tmp_path / "empty", tmp_path / "empty", "empty folder"


def _folder_of_text(tmp_path):
    folder = tmp_path / "docs"
    folder.mkdir()
    (folder / "notes.txt").write_text("hello")
    return folder, folder, "no DICOM image files"


def _truncated_dicom(tmp_path):
    folder = write_dicom_series(_volume(), tmp_path / "trunc")
    victim = sorted(folder.iterdir())[4]
    victim.write_bytes(victim.read_bytes()[:-300])
    return folder, victim, "corrupt DICOM"


def _garbage_dicom(tmp_path):
    folder = write_dicom_series(_volume(), tmp_path / "garbage")
    victim = sorted(folder.iterdir())[2]
    victim.write_bytes(victim.read_bytes()[:132] + b"\xff" * 64)
    return folder, victim, "corrupt DICOM"


def _mr_series(tmp_path):
    folder = write_dicom_series(_volume(), tmp_path / "mr")
    for f in folder.iterdir():
        ds = pydicom.dcmread(f)
        ds.Modality = "MR"
        ds.save_as(f)
    return folder, folder, "modality MR"


def _duplicate_slice(tmp_path):
    folder = write_dicom_series(_volume(), tmp_path / "dup")
    ds = pydicom.dcmread(sorted(folder.iterdir())[3])
    ds.SOPInstanceUID = generate_uid()
    ds.save_as(folder / "slice_00003b.dcm")
    return folder, folder / "slice_00003b.dcm", "duplicate slice"


def _unknown_suffix(tmp_path):
    path = tmp_path / "scan.png"
    path.write_bytes(b"\x89PNG")
    return path, path, "unknown volume format"


def _missing_path(tmp_path):
    return tmp_path / "nothing.nii", tmp_path / "nothing.nii", "no such file"


@pytest.mark.parametrize(
    "make",
    [_non_ct_nifti, _flat_nifti, _empty_folder, _folder_of_text, _truncated_dicom, _garbage_dicom, _mr_series,
     _duplicate_slice, _unknown_suffix, _missing_path],
)
def test_bad_input_raises_input_error_naming_the_file(tmp_path, make):
    given, named, message = make(tmp_path)
    with pytest.raises(InputError, match=message) as info:
        read_volume(given)
    assert info.value.path == str(named)


def test_writers_refuse_non_finite_values_and_leave_nothing(tmp_path):
    volume = _volume()
    hu = volume.hu.copy()
    hu[2, 3, 4] = np.nan
    bad = CTVolume(hu=hu, affine=volume.affine)
    with pytest.raises(InputError, match="not finite"):
        write_dicom_series(bad, tmp_path / "out")
    with pytest.raises(InputError, match="not finite"):
        write_nifti(bad, tmp_path / "out.nii")
    assert list(tmp_path.iterdir()) == []


def test_nifti_scaling_is_applied(tmp_path):
    stored = np.arange(-1000, 1000, dtype=np.int16).reshape(10, 10, 20)  # nibabel order [i, j, k]
    image = nib.Nifti1Image(stored, np.diag([0.5, 0.5, 2.0, 1.0]))
    image.header.set_slope_inter(2.0, -24.0)
    nib.save(image, str(tmp_path / "scaled.nii"))
    back = read_volume(tmp_path / "scaled.nii")
    np.testing.assert_array_equal(back.hu, stored.transpose(2, 1, 0) * 2.0 - 24.0)
    np.testing.assert_allclose(back.spacing_mm, [0.5, 0.5, 2.0])
