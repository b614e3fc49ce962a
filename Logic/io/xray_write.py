"""Writing an X-ray: ``write_xray_dicom`` (uncompressed explicit VR little endian 16-bit MONOCHROME2 DICOM
carrying the geometry; the principal point in a private CarmReg block, group 0029) and ``write_png16`` (16-bit
grey PNG). Both atomic. See ``xray`` for the tags and their meaning.
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

import numpy as np

from carmreg.logic.geometry.camera import CarmIntrinsics
from carmreg.logic.io.atomic import atomic_write
from carmreg.logic.io.dicom_common import ds_decimal
from carmreg.logic.io.xray_image import PRIVATE_CREATOR, PRIVATE_GROUP, PRIVATE_PRINCIPAL_POINT, SOP_CLASS_UIDS


def _dicom_uids(modality: str):
    from pydicom.uid import generate_uid

    if modality not in SOP_CLASS_UIDS:
        raise ValueError(f"modality must be one of {sorted(SOP_CLASS_UIDS)}, got {modality!r}")
    return SOP_CLASS_UIDS[modality], generate_uid(), generate_uid(), generate_uid()


def write_xray_dicom(path: str | Path, pixels_uint16: np.ndarray, intrinsics: CarmIntrinsics, *,
                     sod_mm: float | None = None, modality: str = "XA", patient_name: str = "CarmReg^Sample",
                     bone_dark: bool = True, storage: str = "log-display") -> Path:
    """Write a single-frame 16-bit MONOCHROME2 X-ray DICOM (explicit VR little endian), atomically.

    pixels_uint16: (rows, columns) image[row, column]; must match ``intrinsics.size_px``.
    Geometry written: DistanceSourceToDetector = sdd_mm, ImagerPixelSpacing = [row spacing, column
    spacing] (DICOM order), DistanceSourceToPatient and EstimatedRadiographicMagnificationFactor =
    sdd/sod when ``sod_mm`` is given, the principal point in private tag (0029,1001) "CarmReg".
    ``bone_dark`` sets PixelIntensityRelationshipSign (+1 bone dark, -1 bone bright); ``storage`` sets
    PixelIntensityRelationship: "log-display" LOG (CarmReg's simulator writes a log display), "linear-intensity" LIN
    (the X-ray intensity itself, which a reader may then convert with -log: ``XrayImage.stated_storage``).
    """
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian

    pixels = np.asarray(pixels_uint16)
    if pixels.ndim != 2 or pixels.dtype != np.uint16:
        raise ValueError(f"pixels_uint16 must be a 2D uint16 array, got {pixels.dtype} {pixels.shape}")
    if (pixels.shape[1], pixels.shape[0]) != tuple(intrinsics.size_px):
        raise ValueError(f"image is {pixels.shape[1]}x{pixels.shape[0]} px but intrinsics.size_px is "
                         f"{intrinsics.size_px}")
    if storage not in ("log-display", "linear-intensity"):
        raise ValueError(f"storage must be 'log-display' or 'linear-intensity', got {storage!r}")
    sop_class, sop_instance, study_uid, series_uid = _dicom_uids(modality)
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = sop_instance
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    now = _dt.datetime.now()
    ds.SOPClassUID, ds.SOPInstanceUID = sop_class, sop_instance
    ds.StudyInstanceUID, ds.SeriesInstanceUID = study_uid, series_uid
    ds.Modality = modality
    ds.PatientName, ds.PatientID = patient_name, "CARMREG"
    ds.StudyDate = ds.SeriesDate = ds.ContentDate = now.strftime("%Y%m%d")
    ds.StudyTime = ds.SeriesTime = ds.ContentTime = now.strftime("%H%M%S")
    ds.SeriesNumber, ds.InstanceNumber = 1, 1
    ds.ImageType = ["DERIVED", "SECONDARY", "SINGLE PLANE"] if modality in ("XA", "RF") else ["DERIVED",
                                                                                             "SECONDARY"]
    ds.Manufacturer = "CarmReg"
    _set_pixels(ds, pixels)
    ds.PixelIntensityRelationship = "LIN" if storage == "linear-intensity" else "LOG"
    ds.PixelIntensityRelationshipSign = 1 if bone_dark else -1
    _set_geometry(ds, intrinsics, sod_mm)
    atomic_write(path, lambda tmp: ds.save_as(tmp, enforce_file_format=True))
    return Path(path)


def _set_pixels(ds, pixels: np.ndarray) -> None:
    ds.Rows, ds.Columns = int(pixels.shape[0]), int(pixels.shape[1])
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, 16, 15
    ds.PixelRepresentation = 0
    ds.PixelData = np.ascontiguousarray(pixels, dtype="<u2").tobytes()


def _set_geometry(ds, intrinsics: CarmIntrinsics, sod_mm: float | None) -> None:
    du, dv = intrinsics.pixel_spacing_mm
    ds.DistanceSourceToDetector = ds_decimal(intrinsics.sdd_mm)
    ds.ImagerPixelSpacing = [ds_decimal(dv), ds_decimal(du)]  # DICOM order: row spacing \ column spacing
    if sod_mm is not None:
        ds.DistanceSourceToPatient = ds_decimal(sod_mm)
        ds.EstimatedRadiographicMagnificationFactor = ds_decimal(intrinsics.sdd_mm / sod_mm)
    block = ds.private_block(PRIVATE_GROUP, PRIVATE_CREATOR, create=True)
    block.add_new(PRIVATE_PRINCIPAL_POINT, "DS", [ds_decimal(x) for x in intrinsics.principal_point_px])




def write_png16(path: str | Path, pixels_uint16: np.ndarray) -> Path:
    """Write a (rows, columns) uint16 image as a 16-bit greyscale PNG, atomically."""
    from PIL import Image

    pixels = np.asarray(pixels_uint16)
    if pixels.ndim != 2 or pixels.dtype != np.uint16:
        raise ValueError(f"pixels_uint16 must be a 2D uint16 array, got {pixels.dtype} {pixels.shape}")
    image = Image.fromarray(np.ascontiguousarray(pixels))
    atomic_write(path, lambda tmp: image.save(tmp, format="PNG"))
    return Path(path)
