"""Reading and writing CT volumes: DICOM series, NIfTI, NRRD, MetaImage -> ``Volume`` (HU, LPS mm).

Every reader returns ``Volume(hu, ijk_to_lps)`` with ``hu[i, j, k]`` (i fastest in the file) and the 4x4
voxel-centre-index -> LPS mm affine (see ``geometry.volume``). HU stay int16 when the file's values are
integers that fit int16; otherwise they become float32.

Formats
-------
- DICOM series (a folder, or one slice file whose folder holds the series) or one enhanced multi-frame
  CT file (``dicom_ct``). CT only; slices sorted along the slice normal; spacing from
  ImagePositionPatient.
- NIfTI ``.nii`` / ``.nii.gz`` (nibabel): world is RAS; the sform is used when its code is set, else the
  qform, else nibabel's fallback (flagged in ``meta``). ``ijk_to_lps = diag(-1, -1, 1, 1) @ ijk_to_ras``.
  Scaling (scl_slope/scl_inter) is applied.
- NRRD ``.nrrd`` / ``.nhdr`` (pynrrd): ``space directions`` (one row per axis) and ``space origin`` (centre
  of the first voxel) in the named ``space``: left-posterior-superior / LPS as is, right-anterior-superior
  / RAS and left-anterior-superior / LAS converted to LPS; spaces without anatomical meaning
  (scanner-xyz, 3D-right-handed, none) are taken as LPS and flagged in ``meta``.
- MetaImage ``.mha`` / ``.mhd`` (own reader): ``TransformMatrix`` (row a = LPS direction of index axis a,
  as ITK writes it), ``Offset`` (centre of the first voxel), ``ElementSpacing``, ``ElementType``,
  ``ElementDataFile`` LOCAL or one external raw file, ``CompressedData`` (zlib), byte order.
  MetaImage worlds are LPS (ITK); ``AnatomicalOrientation`` is recorded in ``meta`` only.

Every reader estimates the memory first and refuses volumes above ``MAX_VOLUME_BYTES`` (8 GiB). Every
reader refuses what would give a silently wrong volume: fewer than 2 voxels along an axis, NaN or infinite
voxel values, a singular or non-finite affine; and turns every failure of the underlying library on a
damaged file into an ``InputFileError`` naming the file.
"""

from __future__ import annotations

from pathlib import Path

from carmreg.logic.errors import InputFileError
from carmreg.logic.geometry.volume import Volume
from carmreg.logic.io.dicom_common import has_dicom_marker, quiet_libraries
from carmreg.logic.io.dicom_ct import load_dicom_file, load_dicom_series
from carmreg.logic.io.dicom_ct_write import write_dicom_series
from carmreg.logic.io.limits import regular_file
from carmreg.logic.io.metaimage import load_metaimage
from carmreg.logic.io.nifti import load_nifti
from carmreg.logic.io.nrrd_volume import load_nrrd, write_volume_nrrd

__all__ = ["load_dicom_series", "load_volume", "write_dicom_series", "write_volume_nrrd"]

SUPPORTED = "a DICOM series folder, .nii/.nii.gz, .nrrd/.nhdr or .mha/.mhd"


def load_volume(path: str | Path, *, series_uid: str | None = None) -> Volume:
    """Read a CT from a DICOM series folder (or one of its files), NIfTI, NRRD or MetaImage.

    series_uid: which DICOM series to read when the folder holds more than one.
    Raises InputFileError with an actionable message for anything a user can fix.
    """
    path = Path(path)
    if not path.exists():
        raise InputFileError(f"{path}: CT not found; give {SUPPORTED}")
    if not path.is_dir():
        regular_file(path, "CT")
        if path.stat().st_size == 0:
            raise InputFileError(f"{path}: file is empty")
    with quiet_libraries() as notes:
        try:
            volume = _read_any(path, series_uid)
        except OSError as exc:  # permission denied, I/O error, symlink loop: one line, not a traceback
            raise InputFileError(f"{getattr(exc, 'filename', None) or path}: the CT cannot be read "
                                 f"({exc.strerror or exc}); check its permissions or copy it again") from None
    if notes:
        volume.meta["library_warnings"] = notes
    return volume


def _read_any(path: Path, series_uid: str | None) -> Volume:
    if path.is_dir():
        return load_dicom_series(path, series_uid=series_uid)
    name = path.name.lower()
    if name.endswith((".nii", ".nii.gz")):
        return load_nifti(path)
    if name.endswith((".nrrd", ".nhdr")):
        return load_nrrd(path)
    if name.endswith((".mha", ".mhd")):
        return load_metaimage(path)
    if name.endswith((".dcm", ".dicom", ".ima")) or has_dicom_marker(path):
        return load_dicom_file(path, series_uid=series_uid)
    raise InputFileError(f"{path}: unknown CT format; give {SUPPORTED}")

