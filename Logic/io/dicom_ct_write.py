"""Writing a CT as a DICOM series (CT Image Storage, one file per slice, atomic each): used for the sample case
and the tests that prove a series round-trips.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from carmreg.logic.errors import InputFileError
from carmreg.logic.geometry.volume import Volume
from carmreg.logic.io.atomic import atomic_write
from carmreg.logic.io.dicom_ct import CT_IMAGE_STORAGE


def write_dicom_series(folder: str | Path, volume: Volume, *, patient_name: str = "CarmReg^Sample",
                       series_description: str = "CarmReg CT") -> list[Path]:
    """Write a Volume as a CT DICOM series (one file per k slice, explicit VR little endian), atomically
    per file. HU are stored as int16 (rounded and clipped if the volume is float) with slope 1,
    intercept 0. The i and j axes of ``ijk_to_lps`` must be orthogonal (any k step, e.g. a tilt, is fine).
    Refuses a folder that already holds .dcm files (two series would mix)."""
    folder = Path(folder)
    if folder.is_dir() and any(folder.glob("*.dcm")):
        raise InputFileError(f"{folder}: already holds DICOM files; choose an empty folder")
    template = _ct_template(volume, patient_name, series_description)
    hu = np.asarray(volume.hu)
    if hu.dtype != np.int16:
        hu = np.clip(np.rint(hu), -32768, 32767).astype(np.int16)
    affine = volume.ijk_to_lps
    normal = np.cross(affine[:3, 0], affine[:3, 1])
    normal /= np.linalg.norm(normal)
    paths = []
    for k in range(hu.shape[2]):
        position = affine[:3, 3] + k * affine[:3, 2]
        paths.append(_write_ct_slice(folder / f"slice_{k:04d}.dcm", template, hu[:, :, k].T, k, position,
                                     float(position @ normal)))
    return paths


def _ct_template(volume: Volume, patient_name: str, series_description: str):
    """Dataset with everything shared by the slices of one written series."""
    import datetime

    from pydicom.dataset import Dataset
    from pydicom.uid import generate_uid

    from carmreg.logic.io.dicom_common import ds_decimal

    affine = volume.ijk_to_lps
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    row_dir, col_dir = affine[:3, 0] / spacing[0], affine[:3, 1] / spacing[1]
    if abs(row_dir @ col_dir) > 1e-6:
        raise ValueError("write_dicom_series: the i and j axes of ijk_to_lps are not orthogonal")
    normal = np.cross(row_dir, col_dir)
    now = datetime.datetime.now()
    ds = Dataset()
    ds.SOPClassUID, ds.Modality = CT_IMAGE_STORAGE, "CT"
    ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = (generate_uid() for _ in range(3))
    ds.PatientName, ds.PatientID, ds.SeriesDescription = patient_name, "CARMREG", series_description
    ds.StudyDate = ds.SeriesDate = now.strftime("%Y%m%d")
    ds.StudyTime = ds.SeriesTime = now.strftime("%H%M%S")
    ds.SeriesNumber, ds.ImageType = 1, ["DERIVED", "SECONDARY", "AXIAL"]
    ds.ImageOrientationPatient = [ds_decimal(x) for x in (*row_dir, *col_dir)]
    ds.PixelSpacing = [ds_decimal(spacing[1]), ds_decimal(spacing[0])]  # row spacing \ column spacing
    ds.SliceThickness = ds_decimal(abs(affine[:3, 2] @ normal))
    ds.Rows, ds.Columns = int(volume.shape[1]), int(volume.shape[0])
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
    ds.RescaleIntercept, ds.RescaleSlope, ds.RescaleType = "0", "1", "HU"
    return ds


def _write_ct_slice(path: Path, template, pixels_rc: np.ndarray, k: int, position: np.ndarray,
                    depth: float) -> Path:
    import copy

    from pydicom.dataset import FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    from carmreg.logic.io.dicom_common import ds_decimal

    ds = copy.deepcopy(template)
    ds.SOPInstanceUID = generate_uid()
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = ds.SOPClassUID, ds.SOPInstanceUID
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta = meta
    ds.InstanceNumber = k + 1
    ds.ImagePositionPatient = [ds_decimal(x) for x in position]
    ds.SliceLocation = ds_decimal(depth)
    ds.PixelData = np.ascontiguousarray(pixels_rc, dtype="<i2").tobytes()
    atomic_write(path, lambda tmp: ds.save_as(tmp, enforce_file_format=True))
    return path
