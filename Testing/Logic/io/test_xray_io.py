"""X-ray reading and writing: DICOM geometry and its sources, polarity, frames, PNG/TIFF, bad files."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pydicom
import pytest
from PIL import Image

from carmreg.logic.errors import GeometryError, InputFileError
from carmreg.logic.geometry.camera import CarmIntrinsics
from carmreg.logic.io.xray import load_xray, write_png16, write_xray_dicom

ROWS, COLS = 30, 40


@pytest.fixture
def pixels() -> np.ndarray:
    """A (rows, cols) uint16 ramp whose every pixel differs: value = 40 * row + col, times 13."""
    return (np.arange(ROWS * COLS, dtype=np.uint16).reshape(ROWS, COLS) * 13).astype(np.uint16)


@pytest.fixture
def intrinsics() -> CarmIntrinsics:
    return CarmIntrinsics(1010.0, (0.30, 0.25), (COLS, ROWS), (18.25, 16.5))


@pytest.fixture
def xa_path(tmp_path, pixels, intrinsics):
    return write_xray_dicom(tmp_path / "xa.dcm", pixels, intrinsics, sod_mm=640.0)


def _edit(path, **changes):
    ds = pydicom.dcmread(path)
    for key, value in changes.items():
        if value is None:
            delattr(ds, key)
        else:
            setattr(ds, key, value)
    ds.save_as(path)
    return path


# ----------------------------------------------------------------------------------------------- DICOM

def test_dicom_round_trip_geometry_and_sources(xa_path, pixels, intrinsics):
    ds = pydicom.dcmread(xa_path)
    assert ds.file_meta.TransferSyntaxUID == pydicom.uid.ExplicitVRLittleEndian
    assert ds.PhotometricInterpretation == "MONOCHROME2" and ds.BitsStored == 16
    assert [float(x) for x in ds.ImagerPixelSpacing] == [0.25, 0.30]  # DICOM order: row \ column
    image = load_xray(xa_path)
    assert image.pixels.dtype == np.float32 and image.pixels.shape == (ROWS, COLS)
    np.testing.assert_array_equal(image.pixels, pixels)
    assert image.intrinsics == intrinsics  # sdd, (column, row) spacing, size, principal point
    assert image.sod_mm == 640.0 and image.bone_dark is True and image.size_px == (COLS, ROWS)
    assert image.sources["sdd_mm"] == "DICOM (0018,1110) DistanceSourceToDetector"
    assert image.sources["pixel_spacing_mm"] == "DICOM (0018,1164) ImagerPixelSpacing"
    assert image.sources["sod_mm"] == "DICOM (0018,1111) DistanceSourceToPatient"
    assert image.sources["principal_point_px"].startswith("DICOM private")
    assert image.intrinsics.sources["sdd_mm"] == image.sources["sdd_mm"]
    assert image.meta["EstimatedRadiographicMagnificationFactor"] == pytest.approx(1010.0 / 640.0, 1e-9)
    assert image.meta["modality"] == "XA" and image.meta["n_frames"] == 1


def test_manual_values_override_and_complete(xa_path):
    image = load_xray(xa_path, sdd_mm=1200.0, pixel_spacing_mm=0.2, principal_point_px=(10.0, 11.0),
                      sod_mm=700.0)
    assert image.intrinsics.sdd_mm == 1200.0 and image.intrinsics.pixel_spacing_mm == (0.2, 0.2)
    assert image.intrinsics.principal_point_px == (10.0, 11.0) and image.sod_mm == 700.0
    assert all(image.sources[k] == "manual" for k in ("sdd_mm", "pixel_spacing_mm", "principal_point_px",
                                                      "sod_mm"))
    image = load_xray(_edit(xa_path, DistanceSourceToDetector=None), sdd_mm=980.0)
    assert image.intrinsics.sdd_mm == 980.0 and image.sources["sdd_mm"] == "manual"
    assert image.intrinsics.pixel_spacing_mm == (0.30, 0.25)
    assert image.sources["pixel_spacing_mm"].startswith("DICOM (0018,1164)")


def test_missing_geometry_names_the_flag(xa_path):
    image = load_xray(_edit(xa_path, DistanceSourceToDetector=None))
    assert image.intrinsics is None and "sdd_mm" not in image.sources
    with pytest.raises(GeometryError, match="--sdd-mm") as err:
        image.require_intrinsics()
    assert "--pixel-spacing-mm" not in str(err.value)
    image = load_xray(_edit(xa_path, ImagerPixelSpacing=None))
    with pytest.raises(GeometryError, match="--sdd-mm.*--pixel-spacing-mm"):
        image.require_intrinsics()


def test_pixel_spacing_fallback_is_flagged(xa_path):
    _edit(xa_path, ImagerPixelSpacing=None, PixelSpacing=["0.2", "0.15"])
    image = load_xray(xa_path)
    assert image.intrinsics.pixel_spacing_mm == (0.15, 0.2)  # (column, row)
    assert "may be calibrated" in image.sources["pixel_spacing_mm"]
    assert "--pixel-spacing-mm" in image.meta["warning_pixel_spacing"]


def test_principal_point_defaults_to_centre(tmp_path, pixels):
    path = write_xray_dicom(tmp_path / "a.dcm", pixels, CarmIntrinsics(1000.0, (0.3, 0.3), (COLS, ROWS)))
    ds = pydicom.dcmread(path)
    del ds[0x00291001]
    ds.save_as(path)
    image = load_xray(path)
    assert image.intrinsics.principal_point_px == (19.5, 14.5)
    assert image.sources["principal_point_px"] == "default (detector centre)"
    assert image.sod_mm is None and "sod_mm" not in image.sources


def test_implausible_geometry_in_file_is_a_geometry_error(xa_path):
    _edit(xa_path, DistanceSourceToDetector="5")
    with pytest.raises(GeometryError, match="--sdd-mm"):
        load_xray(xa_path)
    assert load_xray(xa_path, sdd_mm=1000.0).intrinsics.sdd_mm == 1000.0  # the manual value repairs it


@pytest.mark.parametrize("bits", [16, 12])
def test_monochrome1_inverted(xa_path, pixels, bits):
    stored = (pixels.astype(np.int64) % (2**bits)).astype(np.uint16)
    ds = pydicom.dcmread(xa_path)
    ds.PixelData = stored.astype("<u2").tobytes()
    ds.PhotometricInterpretation, ds.BitsStored, ds.HighBit = "MONOCHROME1", bits, bits - 1
    ds.PixelIntensityRelationship = "LOG"
    ds.save_as(xa_path)
    image = load_xray(xa_path)
    np.testing.assert_array_equal(image.pixels, (2**bits - 1) - stored.astype(np.float32))
    assert image.bone_dark is False  # sign +1 (bone dark when stored) flipped by MONOCHROME1
    assert "MONOCHROME1" in image.sources["bone_dark"] and "note_inverted" in image.meta


@pytest.mark.parametrize("relationship, sign, kept", [("LIN", 1, True), ("LIN", -1, False), ("LOG", 1, False)])
def test_monochrome1_linear_intensities_are_kept_as_stored(xa_path, pixels, relationship, sign, kept):
    """MONOCHROME1 with LIN and sign +1 stores the X-ray intensity itself, whose -log is the attenuation: the
    values are kept (shown bone dark, as the sign says), not inverted into something neither linear nor log."""
    stored = pixels.astype(np.uint16)
    _edit(xa_path, PhotometricInterpretation="MONOCHROME1", PixelIntensityRelationship=relationship,
          PixelIntensityRelationshipSign=sign)
    image = load_xray(xa_path)
    expected = stored.astype(np.float32) if kept else 65535.0 - stored.astype(np.float32)
    np.testing.assert_array_equal(image.pixels, expected)
    assert image.bone_dark is (kept or (sign == -1))  # kept: bone dark; inverted: the sign flipped
    assert ("note_linear_intensity" in image.meta) is kept and ("note_inverted" in image.meta) is not kept


@pytest.mark.parametrize("photometric", ["MONOCHROME1", "MONOCHROME2"])
@pytest.mark.parametrize("relationship, sign, stated", [("LIN", 1, "linear-intensity"), ("LIN", -1, None),
                                                        ("LOG", 1, None), (None, None, None)])
def test_a_file_that_stores_the_intensity_itself_states_linear_storage(xa_path, photometric, relationship, sign,
                                                                       stated):
    """PixelIntensityRelationship LIN with sign +1 (either photometric interpretation) states linear intensity,
    which the appearance then uses; anything else leaves the storage to the image."""
    changes = {"PhotometricInterpretation": photometric}
    changes.update({k: v for k, v in (("PixelIntensityRelationship", relationship),
                                      ("PixelIntensityRelationshipSign", sign)) if v is not None})
    image = load_xray(_edit(xa_path, **changes))
    assert image.stated_storage == stated
    assert ("storage" in image.sources) is (stated is not None)


@pytest.mark.parametrize("modality, sign, expected", [("XA", None, True), ("RF", None, True),
                                                      ("DX", None, False), ("CR", None, False),
                                                      ("DX", 1, True), ("XA", -1, False)])
def test_bone_dark_from_sign_or_modality_default(tmp_path, pixels, intrinsics, modality, sign, expected):
    path = write_xray_dicom(tmp_path / "a.dcm", pixels, intrinsics, modality=modality)
    _edit(path, PixelIntensityRelationshipSign=sign)
    image = load_xray(path)
    assert image.bone_dark is expected and image.meta["modality"] == modality
    assert ("default" in image.sources["bone_dark"]) == (sign is None)
    assert image.polarity_stated == (sign is not None)  # a stated polarity is evidence (image.appearance)
    assert load_xray(path, bone_dark=not expected).bone_dark is (not expected)


def _multiframe(path, frames: np.ndarray):
    ds = pydicom.dcmread(path)
    ds.NumberOfFrames = len(frames)
    ds.PixelData = frames.astype("<u2").tobytes()
    ds.save_as(path)
    return path


def test_multiframe_needs_a_frame(xa_path, pixels):
    frames = np.stack([pixels, pixels + 1, pixels + 2])
    _multiframe(xa_path, frames)
    with pytest.raises(InputFileError, match=r"holds 3 frames; choose one with --frame N \(0 to 2\)"):
        load_xray(xa_path)
    image = load_xray(xa_path, frame=2)
    np.testing.assert_array_equal(image.pixels, pixels + 2)
    assert image.meta["frame"] == 2 and image.meta["n_frames"] == 3 and image.intrinsics is not None
    with pytest.raises(InputFileError, match="--frame -1: frames are counted from 0"):  # never "the last"
        load_xray(xa_path, frame=-1)
    with pytest.raises(InputFileError, match="frame 3 does not exist"):
        load_xray(xa_path, frame=3)


def test_enhanced_multiframe_geometry_from_functional_groups(xa_path, pixels):
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    _multiframe(xa_path, np.stack([pixels, pixels]))
    ds = pydicom.dcmread(xa_path)
    del ds.ImagerPixelSpacing
    measures = Dataset()
    measures.PixelSpacing = ["0.4", "0.5"]  # row \ column
    shared = Dataset()
    shared.PixelMeasuresSequence = Sequence([measures])
    ds.SharedFunctionalGroupsSequence = Sequence([shared])
    ds.save_as(xa_path)
    image = load_xray(xa_path, frame=1)
    assert image.intrinsics.pixel_spacing_mm == (0.5, 0.4)


def test_dicom_bad_files(tmp_path, xa_path):
    raw = xa_path.read_bytes()
    (tmp_path / "cut.dcm").write_bytes(raw[: len(raw) - 700])
    with pytest.raises(InputFileError, match="cut.dcm: cannot decode the DICOM pixel data.*truncated"):
        load_xray(tmp_path / "cut.dcm")
    (tmp_path / "junk.dcm").write_bytes(b"\x00" * 50)
    with pytest.raises(InputFileError, match="junk.dcm"):
        load_xray(tmp_path / "junk.dcm")
    ds = pydicom.dcmread(xa_path)
    del ds.PixelData
    ds.save_as(tmp_path / "nopix.dcm")
    with pytest.raises(InputFileError, match="no PixelData"):
        load_xray(tmp_path / "nopix.dcm")
    (tmp_path / "IM0001").write_bytes(raw)  # PACS export without suffix
    assert load_xray(tmp_path / "IM0001").intrinsics is not None
    (tmp_path / "NOTES").write_text("not an image")
    with pytest.raises(InputFileError, match="NOTES: not a DICOM file"):
        load_xray(tmp_path / "NOTES")
    with pytest.raises(InputFileError, match="modality 'CT' is not an X-ray"):
        load_xray(_edit(xa_path, Modality="CT"))


def test_write_xray_dicom_checks_its_arguments(tmp_path, pixels, intrinsics):
    with pytest.raises(ValueError, match="uint16"):
        write_xray_dicom(tmp_path / "a.dcm", pixels.astype(np.float32), intrinsics)
    with pytest.raises(ValueError, match="size_px"):
        write_xray_dicom(tmp_path / "a.dcm", pixels.T.copy(), intrinsics)
    with pytest.raises(ValueError, match="modality"):
        write_xray_dicom(tmp_path / "a.dcm", pixels, intrinsics, modality="MR")
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------------------------- PNG / TIFF

def test_png16_round_trip_and_manual_geometry(tmp_path, pixels):
    path = write_png16(tmp_path / "x.png", pixels)
    assert Image.open(path).mode.startswith("I")
    image = load_xray(path, sdd_mm=1000.0, pixel_spacing_mm=(0.3, 0.25))
    np.testing.assert_array_equal(image.pixels, pixels)
    assert image.intrinsics.pixel_spacing_mm == (0.3, 0.25) and image.sources["sdd_mm"] == "manual"
    assert image.bone_dark is True and "no polarity in PNG/TIFF/JPEG" in image.sources["bone_dark"]
    assert [p.name for p in tmp_path.iterdir()] == ["x.png"]  # atomic: no temp file left
    bare = load_xray(path)
    assert bare.intrinsics is None
    with pytest.raises(GeometryError, match="--sdd-mm.*--pixel-spacing-mm"):
        bare.require_intrinsics()


@pytest.mark.parametrize("suffix", [".png", ".tif", ".tiff"])
def test_8bit_grey(tmp_path, pixels, suffix):
    grey = (pixels % 256).astype(np.uint8)
    Image.fromarray(grey).save(tmp_path / f"g{suffix}")
    image = load_xray(tmp_path / f"g{suffix}")
    np.testing.assert_array_equal(image.pixels, grey)
    assert image.meta["mode"] == "L"


def test_16bit_tiff(tmp_path, pixels):
    Image.fromarray(pixels).save(tmp_path / "x.tif")
    np.testing.assert_array_equal(load_xray(tmp_path / "x.tif").pixels, pixels)


def test_rgb_with_equal_channels_is_accepted_and_colour_refused(tmp_path, pixels):
    grey = (pixels % 256).astype(np.uint8)
    Image.fromarray(np.stack([grey] * 3, -1)).save(tmp_path / "rgb.png")
    image = load_xray(tmp_path / "rgb.png")
    np.testing.assert_array_equal(image.pixels, grey)
    assert "equal colour channels" in image.meta["note_channels"]
    Image.fromarray(np.stack([grey] * 3 + [np.full_like(grey, 255)], -1)).save(tmp_path / "rgba.png")
    np.testing.assert_array_equal(load_xray(tmp_path / "rgba.png").pixels, grey)
    colour = np.stack([grey, grey, 255 - grey], -1)
    Image.fromarray(colour).save(tmp_path / "colour.png")
    with pytest.raises(InputFileError, match="colour image.*greyscale"):
        load_xray(tmp_path / "colour.png")


def test_multipage_tiff_needs_a_frame(tmp_path, pixels):
    pages = [Image.fromarray((pixels + k).astype(np.uint16)) for k in range(3)]
    pages[0].save(tmp_path / "run.tif", save_all=True, append_images=pages[1:])
    with pytest.raises(InputFileError, match="holds 3 frames"):
        load_xray(tmp_path / "run.tif")
    np.testing.assert_array_equal(load_xray(tmp_path / "run.tif", frame=1).pixels, pixels + 1)


def test_missing_empty_truncated_and_unknown(tmp_path, pixels):
    with pytest.raises(InputFileError, match="not found"):
        load_xray(tmp_path / "none.png")
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(InputFileError, match="empty"):
        load_xray(tmp_path / "empty.png")
    raw = write_png16(tmp_path / "x.png", pixels).read_bytes()
    (tmp_path / "cut.png").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(InputFileError, match="cut.png: not a readable image.*truncated"):
        load_xray(tmp_path / "cut.png")
    (tmp_path / "x.jpg2").write_bytes(b"abc")
    with pytest.raises(InputFileError, match="unknown X-ray format"):
        load_xray(tmp_path / "x.jpg2")
    with pytest.raises(InputFileError, match="is a folder"):
        load_xray(tmp_path)
    with pytest.raises(GeometryError, match="one number or two"):
        load_xray(tmp_path / "x.png", pixel_spacing_mm=(0.1, 0.2, 0.3))


def test_pydicom_is_imported_by_a_dicom_read_not_by_the_readers(tmp_path):
    """The registration's modules import no pydicom (0.15-0.2 s of every ``carmreg register`` whose files are not
    DICOM); reading a DICOM X-ray does, and a damaged one still gets its one-line error (``dicom_parse_errors``)."""
    damaged = tmp_path / "damaged.dcm"
    damaged.write_bytes(b"\0" * 128 + b"DICM" + b"\x02\x00\x10\x00UI\xff")
    code = ("import sys\nimport carmreg.logic.registration.pipeline\nimport carmreg.logic.io.dicom_ct\n"
            "before = 'pydicom' in sys.modules\nfrom carmreg.logic.io.xray import load_xray\n"
            "from carmreg.logic.errors import CarmRegError\ntry:\n    load_xray(sys.argv[1])\n"
            "except CarmRegError as exc:\n    print(before, 'pydicom' in sys.modules, type(exc).__name__)\n")
    out = subprocess.run([sys.executable, "-c", code, str(damaged)], capture_output=True, text=True, check=True,
                         timeout=120).stdout.split()
    assert out == ["False", "True", "InputFileError"]
