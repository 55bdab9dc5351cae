"""CT volumes: reading (DICOM folder, NIfTI, NRRD, MHA) and writing (NIfTI, DICOM series).

Conventions (every volume bonecad reads or makes follows them):

- ``CTVolume.hu`` is a ``(nk, nj, ni)`` float32 array of Hounsfield units indexed
  ``[k, j, i]``: ``k`` the slice, ``j`` the row, ``i`` the column (numpy's
  ``(z, y, x)`` order for an axial scan).
- ``CTVolume.affine`` is a ``(4, 4)`` matrix taking the homogeneous voxel index
  ``(i, j, k, 1)`` (note: column first) to world coordinates in mm.
- World coordinates are the DICOM patient coordinates, **LPS**: +x towards the
  patient's left, +y posterior, +z superior. NIfTI files store RAS (x and y
  negated); the NIfTI reader and writer convert explicitly. A mesh handed to
  the phantom generator is taken to be in LPS, so mesh -> CT -> mesh returns
  the mesh in its own frame.
"""
from __future__ import annotations

import gzip
import hashlib
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bonecad.errors import InputError
from bonecad.staging import staged_file, staged_output

log = logging.getLogger(__name__)

# NIfTI world (RAS) <-> DICOM/ITK world (LPS): negate x and y.
RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])

# A CT holds air (about -1000 HU) or fat (about -100 HU) somewhere, and tissue
# denser than water; an image whose values never go below this is not in HU.
_CT_MIN_BELOW_HU = -200.0
_CT_MAX_ABOVE_HU = 200.0
# Slices whose positions differ from a regular grid by more than this share of
# the spacing are resampled onto a regular grid.
_SPACING_TOLERANCE = 0.01
# Direction cosines this close are taken as equal (about 0.06 degrees).
_ORIENTATION_TOLERANCE = 1e-3


@dataclass(frozen=True)
class CTVolume:
    """A CT volume on a regular (possibly sheared, for gantry tilt) grid.

    hu : (nk, nj, ni) float32, Hounsfield units, indexed [k, j, i]
    affine : (4, 4) float64, voxel index (i, j, k, 1) -> LPS world, mm
    source : the file or folder read ("" for a generated volume)
    missing_slices : slice indices k absent from the acquisition; their data
        in ``hu`` is interpolated from the neighbouring slices
    """

    hu: np.ndarray
    affine: np.ndarray
    source: str = ""
    missing_slices: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if self.hu.ndim != 3:
            raise InputError(f"a CT volume must be 3-D, got shape {self.hu.shape}", self.source or None)
        if self.affine.shape != (4, 4) or abs(np.linalg.det(self.affine[:3, :3])) < 1e-12:
            raise InputError("the voxel-to-world matrix is singular or not 4x4", self.source or None)

    @property
    def shape(self) -> tuple[int, int, int]:
        """(nk, nj, ni) voxels."""
        return tuple(int(n) for n in self.hu.shape)  # type: ignore[return-value]

    @property
    def spacing_mm(self) -> np.ndarray:
        """(3,) voxel step lengths along i, j, k in mm."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    def index_to_world(self, ijk: np.ndarray) -> np.ndarray:
        """(n, 3) voxel indices (i, j, k), fractional allowed -> (n, 3) LPS mm."""
        ijk = np.asarray(ijk, dtype=np.float64)
        return ijk @ self.affine[:3, :3].T + self.affine[:3, 3]

    def world_to_index(self, xyz: np.ndarray) -> np.ndarray:
        """(n, 3) LPS mm -> (n, 3) fractional voxel indices (i, j, k)."""
        xyz = np.asarray(xyz, dtype=np.float64)
        return (xyz - self.affine[:3, 3]) @ np.linalg.inv(self.affine[:3, :3]).T


def check_hounsfield(hu: np.ndarray, path: object) -> None:
    """Raise InputError unless ``hu`` spans a CT's range (air or fat and dense tissue)."""
    low, high = float(np.min(hu)), float(np.max(hu))
    if not np.isfinite(low) or not np.isfinite(high):
        raise InputError("the image holds NaN or infinite values", path)
    if low > _CT_MIN_BELOW_HU or high < _CT_MAX_ABOVE_HU:
        raise InputError(
            f"not a CT image in Hounsfield units: values run from {low:.0f} to {high:.0f} "
            f"(a CT has air or fat below {_CT_MIN_BELOW_HU:.0f} HU and tissue above {_CT_MAX_ABOVE_HU:.0f} HU)",
            path,
        )


# ---------------------------------------------------------------- reading


def read_volume(path: str | Path, *, max_slice_gap_mm: float = 5.0) -> CTVolume:
    """Read a CT volume: a DICOM folder (or one file of the series), .nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd.

    Irregular DICOM slice spacing is resampled linearly onto a regular grid;
    a gap wider than ``max_slice_gap_mm`` raises InputError. Gantry tilt is
    kept exactly as a sheared affine. Raises InputError, naming the file, on
    anything that is not a readable CT.
    """
    path = Path(path)
    if not path.exists():
        raise InputError("no such file or folder", path)
    name = path.name.lower()
    if path.is_dir():
        volume = _read_dicom_folder(path, max_slice_gap_mm)
    elif name.endswith((".nii", ".nii.gz")):
        volume = _read_nifti(path)
    elif name.endswith((".nrrd", ".nhdr", ".mha", ".mhd")):
        volume = _read_itk(path)
    elif name.endswith((".dcm", ".ima")) or _has_dicom_preamble(path):
        volume = _read_dicom_folder(path.parent, max_slice_gap_mm, wanted=path)
    else:
        raise InputError(
            "unknown volume format (expected a DICOM folder, .nii, .nii.gz, .nrrd, .nhdr, .mha or .mhd)", path
        )
    check_hounsfield(volume.hu, path)
    return volume


def _read_nifti(path: Path) -> CTVolume:
    import nibabel as nib
    from nibabel.arrayproxy import ArrayProxy
    from nibabel.spatialimages import SpatialImage

    try:
        image = nib.load(str(path))
        if not isinstance(image, SpatialImage):
            raise TypeError(f"{type(image).__name__} is not an image with an affine")
        proxy = image.dataobj
        if not isinstance(proxy, ArrayProxy):
            raise TypeError(f"the image data is held as {type(proxy).__name__}, not read from the file")
        # Unscaled stored values (a memory map for .nii), scaled slice by slice in float32.
        raw = np.squeeze(np.asanyarray(proxy.get_unscaled()))
        slope = float(proxy.slope) if np.isfinite(proxy.slope) and proxy.slope != 0 else 1.0
        inter = float(proxy.inter) if np.isfinite(proxy.inter) else 0.0
    except Exception as exc:  # nibabel raises many kinds on a damaged file
        raise InputError(f"cannot read NIfTI: {exc}", path) from exc
    if raw.ndim != 3:
        raise InputError(f"expected a 3-D image, got shape {raw.shape}", path)
    # nibabel's array is [i, j, k]; bonecad's is [k, j, i].
    hu = np.empty(raw.shape[::-1], dtype=np.float32)
    try:
        for k in range(raw.shape[2]):
            hu[k] = raw[:, :, k].T * np.float32(slope) + np.float32(inter)
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read NIfTI data: {exc}", path) from exc
    affine_ras = np.asarray(image.affine, dtype=np.float64)
    return CTVolume(hu=hu, affine=RAS_TO_LPS @ affine_ras, source=str(path))


def _read_itk(path: Path) -> CTVolume:
    import SimpleITK as sitk

    try:
        image = sitk.ReadImage(str(path))
    except RuntimeError as exc:
        raise InputError(f"cannot read image: {str(exc).strip().splitlines()[-1]}", path) from exc
    if image.GetDimension() != 3 or image.GetNumberOfComponentsPerPixel() != 1:
        raise InputError(
            f"expected a 3-D scalar image, got {image.GetDimension()}-D with "
            f"{image.GetNumberOfComponentsPerPixel()} components",
            path,
        )
    # ITK's physical space is LPS; its array is [k, j, i] already.
    hu = sitk.GetArrayFromImage(image).astype(np.float32, copy=False)
    direction = np.asarray(image.GetDirection(), dtype=np.float64).reshape(3, 3)
    affine = np.eye(4)
    affine[:3, :3] = direction * np.asarray(image.GetSpacing(), dtype=np.float64)
    affine[:3, 3] = image.GetOrigin()
    return CTVolume(hu=np.ascontiguousarray(hu), affine=affine, source=str(path))


def _has_dicom_preamble(path: Path) -> bool:
    try:
        with open(path, "rb") as handle:
            head = handle.read(132)
    except OSError:
        return False
    return len(head) == 132 and head[128:132] == b"DICM"


@dataclass
class _Slice:
    path: Path
    position: np.ndarray  # (3,) ImagePositionPatient, mm
    row_cosine: np.ndarray  # (3,) direction of increasing column index i
    col_cosine: np.ndarray  # (3,) direction of increasing row index j
    spacing: tuple[float, float]  # (between rows, between columns), mm
    size: tuple[int, int]  # (rows, columns)


def _read_dicom_headers(folder: Path) -> tuple[dict[str, list], dict[str, str]]:
    """Headers of every DICOM image below ``folder``, grouped by series UID; and skipped modalities."""
    import pydicom
    from pydicom.errors import InvalidDicomError

    files = sorted(p for p in folder.rglob("*") if p.is_file())
    if not files:
        raise InputError("empty folder: no DICOM files", folder)
    series: dict[str, list] = {}
    other_modalities: dict[str, str] = {}
    for file in files:
        looks_dicom = file.suffix.lower() in (".dcm", ".ima") or _has_dicom_preamble(file)
        try:
            ds = pydicom.dcmread(file, stop_before_pixels=True, force=looks_dicom)
        except InvalidDicomError:
            continue  # not a DICOM file (a README, a thumbnail): ignore it
        except Exception as exc:
            raise InputError(f"corrupt DICOM file: {exc}", file) from exc
        if "SOPClassUID" in ds and str(ds.SOPClassUID) == "1.2.840.10008.1.3.10":
            continue  # DICOMDIR
        if "PixelData" not in ds and "Rows" not in ds:
            if looks_dicom and "ImagePositionPatient" not in ds and "SeriesInstanceUID" not in ds:
                raise InputError("corrupt DICOM file: no image attributes", file)
            continue
        modality = str(ds.get("Modality", "CT"))
        uid = str(ds.get("SeriesInstanceUID", "unknown series"))
        if modality != "CT":
            other_modalities[uid] = modality
            continue
        image_type = [str(v).upper() for v in ds.get("ImageType", [])]
        if "LOCALIZER" in image_type:
            continue
        series.setdefault(uid, []).append((file, ds))
    if not series:
        if other_modalities:
            kinds = ", ".join(sorted(set(other_modalities.values())))
            raise InputError(f"not a CT: the DICOM series are of modality {kinds}", folder)
        raise InputError("no DICOM image files found", folder)
    return series, other_modalities


def _slice_geometry(file: Path, ds) -> _Slice:
    try:
        position = np.asarray([float(v) for v in ds.ImagePositionPatient], dtype=np.float64)
        orientation = np.asarray([float(v) for v in ds.ImageOrientationPatient], dtype=np.float64)
        spacing = tuple(float(v) for v in ds.PixelSpacing)
        size = (int(ds.Rows), int(ds.Columns))
    except (AttributeError, ValueError, TypeError) as exc:
        raise InputError(
            "DICOM slice lacks geometry (ImagePositionPatient, ImageOrientationPatient, PixelSpacing, Rows, Columns)",
            file,
        ) from exc
    if position.shape != (3,) or orientation.shape != (6,) or len(spacing) != 2 or min(spacing) <= 0:
        raise InputError("DICOM slice has malformed geometry attributes", file)
    return _Slice(file, position, orientation[:3], orientation[3:], spacing, size)


def _read_dicom_folder(folder: Path, max_gap_mm: float, wanted: Path | None = None) -> CTVolume:
    import pydicom

    series, _ = _read_dicom_headers(folder)
    if wanted is not None:
        chosen = [uid for uid, items in series.items() if any(f.resolve() == wanted.resolve() for f, _ in items)]
        if not chosen:
            raise InputError("this file is not an image of a CT series", wanted)
        uid = chosen[0]
    else:
        uid = max(series, key=lambda u: (len(series[u]), u))
    items = series[uid]
    if len(items) < 2:
        raise InputError("the CT series has a single slice; a volume needs several", items[0][0])
    slices = [_slice_geometry(f, ds) for f, ds in items]
    first = slices[0]
    for s in slices[1:]:
        if s.size != first.size or not np.allclose(s.spacing, first.spacing, rtol=1e-4):
            raise InputError("slices of one series differ in size or pixel spacing", s.path)
        if not (
            np.allclose(s.row_cosine, first.row_cosine, atol=_ORIENTATION_TOLERANCE)
            and np.allclose(s.col_cosine, first.col_cosine, atol=_ORIENTATION_TOLERANCE)
        ):
            raise InputError("slices of one series differ in orientation (ImageOrientationPatient)", s.path)
    normal = np.cross(first.row_cosine, first.col_cosine)
    heights = np.asarray([s.position @ normal for s in slices])
    order = np.argsort(heights, kind="stable")
    slices = [slices[i] for i in order]
    items = [items[i] for i in order]
    heights = heights[order]
    first = slices[0]
    steps = np.diff(heights)
    if np.any(steps < 1e-3):
        dup = int(np.argmax(steps < 1e-3))
        raise InputError("two slices share one position (duplicate slice)", slices[dup + 1].path)

    # Slice step vector: the along-normal spacing plus any in-plane shift (gantry tilt).
    positions = np.stack([s.position for s in slices])
    offsets = positions - positions[0]
    step_vectors = np.diff(positions, axis=0)
    spacing_k = float(np.median(steps))
    unit_step = np.median(step_vectors / steps[:, None], axis=0)  # step per mm along the normal
    off_line = offsets - heights[:, None] * unit_step + heights[0] * unit_step
    if np.max(np.linalg.norm(off_line, axis=1)) > 0.05 * max(first.spacing):
        raise InputError("slice positions do not lie on a line (irregular gantry tilt or mixed stacks)", folder)
    tilt_deg = float(np.degrees(np.arccos(np.clip(unit_step @ normal / np.linalg.norm(unit_step), -1, 1))))
    if tilt_deg > 0.01:
        log.info("%s: gantry tilt of %.2f degrees kept as a sheared grid", folder, tilt_deg)

    rows, cols = first.size
    hu = np.empty((len(slices), rows, cols), dtype=np.float32)
    for n, (file, _) in enumerate(items):
        try:
            ds = pydicom.dcmread(file)
            pixels = ds.pixel_array
        except Exception as exc:
            raise InputError(f"corrupt DICOM file or unreadable pixel data: {exc}", file) from exc
        if pixels.shape != (rows, cols):
            raise InputError(f"pixel data of shape {pixels.shape}, expected {(rows, cols)}", file)
        slope = float(ds.get("RescaleSlope", 1.0) or 1.0)
        intercept = float(ds.get("RescaleIntercept", 0.0) or 0.0)
        hu[n] = pixels.astype(np.float32) * np.float32(slope) + np.float32(intercept)

    missing: tuple[int, ...] = ()
    irregular = np.max(np.abs(steps - spacing_k)) > _SPACING_TOLERANCE * spacing_k
    if irregular:
        spacing_k = float(np.min(steps))
        if np.max(steps) > max_gap_mm:
            gap = int(np.argmax(steps))
            raise InputError(
                f"slices missing: a gap of {steps[gap]:.2f} mm after this slice (more than {max_gap_mm} mm); "
                "cannot interpolate across it",
                slices[gap].path,
            )
        hu, missing = _resample_slices(hu, heights - heights[0], spacing_k)
        log.info("%s: irregular slice spacing resampled to %.3f mm", folder, spacing_k)

    affine = np.eye(4)
    # PixelSpacing is (row spacing = step along a column = j, column spacing = step along a row = i).
    affine[:3, 0] = first.row_cosine * first.spacing[1]
    affine[:3, 1] = first.col_cosine * first.spacing[0]
    affine[:3, 2] = unit_step * spacing_k
    affine[:3, 3] = first.position
    return CTVolume(hu=hu, affine=affine, source=str(folder), missing_slices=missing)


def _resample_slices(hu: np.ndarray, heights: np.ndarray, spacing: float) -> tuple[np.ndarray, tuple[int, ...]]:
    """Linear interpolation of slices at ``heights`` (mm, from 0) onto a grid of step ``spacing``."""
    count = int(round(heights[-1] / spacing)) + 1
    target = np.arange(count) * spacing
    upper = np.clip(np.searchsorted(heights, target, side="left"), 1, len(heights) - 1)
    lower = upper - 1
    weight = ((target - heights[lower]) / (heights[upper] - heights[lower])).astype(np.float32)
    weight = np.clip(weight, 0.0, 1.0)
    out = np.empty((count,) + hu.shape[1:], dtype=np.float32)
    exact = []
    for n in range(count):
        out[n] = hu[lower[n]] * (1 - weight[n]) + hu[upper[n]] * weight[n]
        exact.append(min(abs(target[n] - heights[lower[n]]), abs(target[n] - heights[upper[n]])) < 0.01 * spacing)
    missing = tuple(int(n) for n in np.flatnonzero(~np.asarray(exact)))
    return out, missing


# ---------------------------------------------------------------- writing


def _check_finite(volume: CTVolume, target: Path) -> None:
    if not np.all(np.isfinite(volume.hu)):
        raise InputError("cannot write the volume: some HU values are not finite", target)


def write_nifti(volume: CTVolume, path: str | Path) -> Path:
    """Write ``volume`` as NIfTI-1 (.nii or .nii.gz), int16 HU, RAS world in the sform/qform. Returns the path."""
    import nibabel as nib

    path = Path(path)
    if not path.name.lower().endswith((".nii", ".nii.gz")):
        raise InputError("a NIfTI file name must end in .nii or .nii.gz", path)
    _check_finite(volume, path)
    data = np.clip(np.rint(volume.hu), -32768, 32767).astype(np.int16).transpose(2, 1, 0)
    affine_ras = RAS_TO_LPS @ volume.affine
    image = nib.Nifti1Image(data, affine_ras)
    image.header.set_xyzt_units("mm")
    linear = affine_ras[:3, :3] / np.linalg.norm(affine_ras[:3, :3], axis=0)
    orthogonal = np.allclose(linear.T @ linear, np.eye(3), atol=1e-6)
    image.set_sform(affine_ras, code=1)
    image.set_qform(affine_ras if orthogonal else None, code=1 if orthogonal else 0)
    payload = image.to_bytes()
    if path.name.lower().endswith(".gz"):
        payload = gzip.compress(payload, compresslevel=6, mtime=0)  # no time stamp: same volume, same file
    with staged_file(path) as tmp:
        tmp.write_bytes(payload)
    return path


def write_dicom_series(volume: CTVolume, folder: str | Path, *, series_description: str = "bonecad phantom") -> Path:
    """Write ``volume`` as a CT DICOM series, one file per slice (missing slices omitted). Returns the folder.

    Pixels are stored as signed 16-bit with RescaleIntercept -1024, RescaleSlope 1.
    """
    import pydicom
    from pydicom.dataset import FileMetaDataset
    from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

    folder = Path(folder)
    _check_finite(volume, folder)
    affine = volume.affine
    row_cos = affine[:3, 0] / np.linalg.norm(affine[:3, 0])
    col_cos = affine[:3, 1] / np.linalg.norm(affine[:3, 1])
    spacing = volume.spacing_mm
    normal = np.cross(row_cos, col_cos)
    thickness = float(abs(affine[:3, 2] @ normal))
    stored = np.clip(np.rint(volume.hu) + 1024, -32768, 32767).astype(np.int16)
    # UIDs derived from the content (pydicom hashes the entropy sources): unique to this volume,
    # and the same volume gives the same files
    content = hashlib.blake2b(stored.tobytes(), digest_size=16)
    content.update(np.ascontiguousarray(affine, dtype=np.float64).tobytes())
    content.update(repr((stored.shape, sorted(volume.missing_slices), series_description)).encode())
    key = content.hexdigest()
    study_uid, series_uid, frame_uid = (generate_uid(entropy_srcs=[key, role]) for role in ("study", "series", "frame"))
    missing = set(volume.missing_slices)
    with staged_output(folder) as stage:
        number = 0
        for k in range(volume.shape[0]):
            if k in missing:
                continue
            number += 1
            meta = FileMetaDataset()
            meta.MediaStorageSOPClassUID = CTImageStorage
            meta.MediaStorageSOPInstanceUID = generate_uid(entropy_srcs=[key, "slice", str(k)])
            meta.TransferSyntaxUID = ExplicitVRLittleEndian
            ds = pydicom.Dataset()
            ds.file_meta = meta
            ds.SOPClassUID = CTImageStorage
            ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
            ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = study_uid, series_uid, frame_uid
            ds.Modality = "CT"
            ds.ImageType = ["DERIVED", "SECONDARY", "AXIAL"]
            ds.PatientName = "bonecad^phantom"
            ds.PatientID = "phantom"
            ds.SeriesDescription = series_description
            ds.SeriesNumber = 1
            ds.InstanceNumber = number
            ds.ImagePositionPatient = [f"{v:.6f}" for v in (affine @ np.array([0.0, 0.0, k, 1.0]))[:3]]
            ds.ImageOrientationPatient = [f"{v:.8f}" for v in np.concatenate([row_cos, col_cos])]
            ds.PixelSpacing = [f"{spacing[1]:.6f}", f"{spacing[0]:.6f}"]
            ds.SliceThickness = f"{thickness:.6f}"
            ds.SpacingBetweenSlices = f"{thickness:.6f}"
            ds.Rows, ds.Columns = volume.shape[1], volume.shape[2]
            ds.SamplesPerPixel = 1
            ds.PhotometricInterpretation = "MONOCHROME2"
            ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
            ds.RescaleIntercept, ds.RescaleSlope, ds.RescaleType = "-1024", "1", "HU"
            ds.PixelData = np.ascontiguousarray(stored[k]).tobytes()
            ds.save_as(stage / f"slice_{k:05d}.dcm", enforce_file_format=True)
    return folder
