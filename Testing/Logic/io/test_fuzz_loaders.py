"""Property-based robustness of every reader: damaged or foreign files load or raise a CarmRegError.

For each format a small valid file is written once; hypothesis then truncates it, flips bits, overwrites
bytes and inserts tokens that break parsers ("nan", "-1", huge numbers, quotes, brackets), and also feeds
random bytes under every suffix. The property, per example:

- the reader either returns a sane object (finite geometry, at least 2 voxels/pixels per axis, finite
  values) or raises a ``CarmRegError`` whose message is one non-empty line naming the file;
- never any other exception (a traceback is a bug), never a hang (a per-example alarm of 10 s, and
  hypothesis' deadline).

Landmark JSON is also fuzzed structurally: documents shaped like Slicer markups or plain JSON whose every
field may be replaced by any JSON value.

Runs in about 15 s (``max_examples`` kept modest); raise ``CARMREG_FUZZ_EXAMPLES`` for a longer hunt.
"""

from __future__ import annotations

import json
import os
import signal
import zlib
from contextlib import contextmanager
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from carmreg.logic.errors import CarmRegError
from carmreg.logic.geometry.camera import CarmIntrinsics
from carmreg.logic.geometry.volume import Volume
from carmreg.logic.io.landmarks import (
    LEVEL_NAMES,
    Landmarks2D,
    Landmarks3D,
    read_landmarks_2d,
    read_landmarks_3d,
    write_landmarks_2d,
    write_landmarks_3d,
)
from carmreg.logic.io.transforms import read_tfm, write_tfm
from carmreg.logic.io.volumes import load_volume, write_dicom_series, write_volume_nrrd
from carmreg.logic.io.xray import XrayImage, load_xray, write_png16, write_xray_dicom

EXAMPLES = int(os.environ.get("CARMREG_FUZZ_EXAMPLES", "30"))
FUZZ = settings(max_examples=EXAMPLES, deadline=5000, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                       HealthCheck.data_too_large])
TOKENS = [b"nan", b"NaN", b"-1", b"0", b"99999999", b"1e308", b"-", b"\n", b"\x00", b" ", b'"', b"[", b"]",
          b",", b"{}", b"\\", b"=", b":"]


# ----------------------------------------------------------------------------------------------- seeds

def _seed_files(folder: Path) -> dict[str, Path]:
    """One small valid file per format (a 6 x 5 x 4 oblique CT, a 16 x 12 X-ray, three landmarks)."""
    rng = np.random.default_rng(0)
    hu = rng.integers(-1000, 2000, size=(6, 5, 4)).astype(np.int16)
    affine = np.array([[0.0, -0.8, 0.0, 10.0], [0.7, 0.0, 0.0, -5.0], [0.0, 0.0, 2.0, 30.0], [0, 0, 0, 1]])
    volume = Volume(hu, affine, "seed")
    seeds = {"nrrd": write_volume_nrrd(folder / "raw.nrrd", volume, compress=False),
             "nrrd_gzip": write_volume_nrrd(folder / "gz.nrrd", volume, compress=True)}
    image = nib.Nifti1Image(hu, np.diag([-0.7, -0.8, 2.0, 1.0]))
    image.set_sform(image.affine, code=2)
    for name in ("ct.nii", "ct.nii.gz"):
        nib.save(image, folder / name)
    seeds["nifti"], seeds["nifti_gz"] = folder / "ct.nii", folder / "ct.nii.gz"
    data = hu.astype("<i2").tobytes(order="F")
    header = ("ObjectType = Image\nNDims = 3\nBinaryDataByteOrderMSB = False\nCompressedData = {}\n"
              "TransformMatrix = 0 1 0 -1 0 0 0 0 1\nOffset = 10 -5 30\nElementSpacing = 0.7 0.8 2\n"
              "DimSize = 6 5 4\nElementType = MET_SHORT\nElementDataFile = LOCAL\n")
    (folder / "ct.mha").write_bytes(header.format("False").encode() + data)
    (folder / "ctz.mha").write_bytes(header.format("True").encode() + zlib.compress(data))
    seeds["mha"], seeds["mha_zlib"] = folder / "ct.mha", folder / "ctz.mha"
    seeds["dicom_ct_slice"] = write_dicom_series(folder / "series", volume)[1]
    pixels = (np.arange(12 * 16, dtype=np.uint16).reshape(12, 16) * 97).astype(np.uint16)
    intrinsics = CarmIntrinsics(1000.0, (0.3, 0.3), (16, 12))
    seeds["dicom_xray"] = write_xray_dicom(folder / "xa.dcm", pixels, intrinsics, sod_mm=600.0)
    seeds["png16"] = write_png16(folder / "x16.png", pixels)
    Image.fromarray((pixels % 251).astype(np.uint8)).save(folder / "x8.png")
    Image.fromarray(pixels).save(folder / "x.tif")
    seeds["png8"], seeds["tiff"] = folder / "x8.png", folder / "x.tif"
    labels = ["T11", "T12", "L1"]
    seeds["mrk_3d"] = write_landmarks_3d(folder / "ct.mrk.json", Landmarks3D(labels, [[1, 2, 60], [1, 3, 30],
                                                                                    [1, 4, 0]]))
    seeds["mrk_2d"] = write_landmarks_2d(folder / "xr.mrk.json",
                                         Landmarks2D(labels, [[3, 2], [4, 5], [6, 8]]), (0.3, 0.3))
    (folder / "lm3.json").write_text(json.dumps({"T11": [1, 2, 60], "T12": [1, 3, 30], "L1": [1, 4, 0]}))
    (folder / "lm2.json").write_text(json.dumps({"T11": [3, 2], "T12": [4, 5], "L1": [6, 8]}))
    (folder / "lm2list.json").write_text(json.dumps([[3, 2], [4, 5], [6, 8]]))
    seeds["json_3d"], seeds["json_2d"], seeds["json_2d_list"] = (folder / n for n in ("lm3.json", "lm2.json",
                                                                                    "lm2list.json"))
    seeds["tfm"] = write_tfm(folder / "t.tfm", affine, center=[1.0, 2.0, 3.0])
    return seeds


READERS = {"nrrd": load_volume, "nrrd_gzip": load_volume, "nifti": load_volume, "nifti_gz": load_volume,
           "mha": load_volume, "mha_zlib": load_volume, "dicom_ct_slice": load_volume,
           "dicom_xray": load_xray, "png16": load_xray, "png8": load_xray, "tiff": load_xray,
           "mrk_3d": read_landmarks_3d, "mrk_2d": read_landmarks_2d, "json_3d": read_landmarks_3d,
           "json_2d": read_landmarks_2d, "json_2d_list": read_landmarks_2d, "tfm": read_tfm}


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> dict[str, Path]:
    return _seed_files(tmp_path_factory.mktemp("seeds"))


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


def test_every_seed_loads(seeds):
    """The unmutated files are valid, so a refusal below is caused by the damage."""
    for name, path in seeds.items():
        assert _sane(READERS[name](path)), name


# ----------------------------------------------------------------------------------------------- property

@contextmanager
def time_limit(seconds: float):
    """Fail (instead of hanging the suite) when the body runs longer than ``seconds``."""
    def expired(*_):
        raise TimeoutError(f"reader still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def _sane(obj) -> bool:
    """What a reader may return: finite geometry and values, at least 2 samples per axis."""
    if isinstance(obj, Volume):
        return (min(obj.shape) >= 2 and np.all(np.isfinite(obj.ijk_to_lps))
                and np.isfinite(float(np.min(obj.hu))) and np.isfinite(float(np.max(obj.hu))))
    if isinstance(obj, XrayImage):
        return (obj.pixels.ndim == 2 and min(obj.pixels.shape) >= 2 and obj.pixels.dtype == np.float32
                and bool(np.all(np.isfinite(obj.pixels))))
    if isinstance(obj, Landmarks3D):
        return obj.points_lps_mm.shape[1:] == (3,) and bool(np.all(np.isfinite(obj.points_lps_mm)))
    if isinstance(obj, Landmarks2D):
        return obj.uv_px.shape[1:] == (2,) and bool(np.all(np.isfinite(obj.uv_px)))
    if isinstance(obj, np.ndarray):  # a transform
        return (obj.shape == (4, 4) and bool(np.all(np.isfinite(obj)))
                and abs(np.linalg.det(obj[:3, :3])) > 1e-9)
    return False


def assert_loads_or_refuses(reader, path: Path) -> None:
    """The property: a sane object, or one CarmRegError line naming the file (or its folder)."""
    try:
        with time_limit(10.0):
            result = reader(path)
    except CarmRegError as exc:
        message = str(exc)
        assert message and "\n" not in message, repr(message)
        assert path.name in message or path.parent.name in message, message
        return
    assert _sane(result), f"{reader.__name__}({path.name}) returned an unusable {type(result).__name__}"


@st.composite
def damage(draw, size: int):
    """A list of edits (truncate / flip a bit / set a byte / insert a token) within ``size`` bytes."""
    position = st.integers(0, max(size - 1, 0))
    edit = st.one_of(st.tuples(st.just("flip"), position, st.integers(0, 7)),
                     st.tuples(st.just("set"), position, st.integers(0, 255)),
                     st.tuples(st.just("insert"), position, st.sampled_from(TOKENS)),
                     st.tuples(st.just("cut"), position, st.just(0)))
    return draw(st.lists(edit, min_size=1, max_size=6))


def apply_damage(raw: bytes, edits) -> bytes:
    data = bytearray(raw)
    for kind, at, value in edits:
        at = min(at, max(len(data) - 1, 0))
        if kind == "cut":
            del data[at:]
        elif not data:
            continue
        elif kind == "flip":
            data[at] ^= 1 << value
        elif kind == "set":
            data[at] = value
        else:
            data[at:at] = value
    return bytes(data)


def _target(name: str, seed: Path, work: Path) -> Path:
    """Where the damaged copy goes: beside intact copies of the other slices for a DICOM series."""
    if name != "dicom_ct_slice":
        return work / seed.name
    folder = work / "series"
    if not folder.is_dir():
        folder.mkdir()
        for other in seed.parent.iterdir():
            (folder / other.name).write_bytes(other.read_bytes())
    return folder / seed.name


@pytest.mark.parametrize("name", list(READERS))
@FUZZ
@given(data=st.data())
def test_damaged_file_loads_or_raises_carmreg_error(seeds, work, name, data):
    raw = seeds[name].read_bytes()
    target = _target(name, seeds[name], work)
    target.write_bytes(apply_damage(raw, data.draw(damage(len(raw)), label="edits")))
    assert_loads_or_refuses(READERS[name], target)


SUFFIXES = {load_volume: [".nrrd", ".nhdr", ".nii", ".nii.gz", ".mha", ".mhd", ".dcm", ""],
            load_xray: [".dcm", ".png", ".tif", ""], read_landmarks_3d: [".mrk.json", ".json"],
            read_landmarks_2d: [".json"], read_tfm: [".tfm", ".txt"]}


@pytest.mark.parametrize("reader, suffix", [(r, s) for r, suffixes in SUFFIXES.items() for s in suffixes],
                         ids=lambda v: getattr(v, "__name__", v or "no-suffix"))
@FUZZ
@given(raw=st.binary(max_size=1200))
def test_random_bytes_are_refused_cleanly(work, reader, suffix, raw):
    target = work / f"random{suffix}"
    target.write_bytes(raw)
    assert_loads_or_refuses(reader, target)


@pytest.mark.parametrize("reader, magic", [(load_volume, b"NRRD0004\n"),
                                           (load_volume, b"ObjectType = Image\n"),
                                           (load_xray, b"\x89PNG\r\n\x1a\n"), (load_xray, b"II*\x00"),
                                           (read_tfm, b"#Insight Transform File V1.0\n")],
                         ids=["nrrd", "mha", "png", "tiff", "tfm"])
@FUZZ
@given(tail=st.binary(max_size=600))
def test_right_magic_then_garbage_is_refused_cleanly(work, reader, magic, tail):
    """Random bytes behind a valid signature reach deeper into each parser than pure noise."""
    suffix = {b"NRRD0004\n": ".nrrd", b"ObjectType = Image\n": ".mha", b"\x89PNG\r\n\x1a\n": ".png",
              b"II*\x00": ".tif"}.get(magic, ".tfm")
    target = work / f"magic{suffix}"
    target.write_bytes(magic + tail)
    assert_loads_or_refuses(reader, target)


# ----------------------------------------------------------------------------------------------- JSON

ANY_JSON = st.recursive(st.none() | st.booleans() | st.integers(-2**70, 2**70) | st.floats()
                        | st.sampled_from(["", "T12", "l1", "X9", "LPS", "RAS", "defined", "undefined"]),
                        lambda inner: (st.lists(inner, max_size=4)
                                       | st.dictionaries(st.text(max_size=4), inner, max_size=3)),
                        max_leaves=8)


def maybe(valid):
    """Mostly the valid shape, sometimes any JSON value in its place."""
    return st.one_of(valid, valid, valid, ANY_JSON)


def numbers(n: int):
    return st.lists(st.floats(-1e4, 1e4) | st.floats(), min_size=n, max_size=n)


LABEL = st.sampled_from(LEVEL_NAMES + ["t 12", "", "X9", "T14"])
POINT = st.fixed_dictionaries(
    {"label": maybe(LABEL), "position": maybe(numbers(3))},
    optional={"positionStatus": maybe(st.sampled_from(["defined", "undefined", "preview"])),
              "carmreg": maybe(st.fixed_dictionaries({"uv_px": maybe(numbers(2))}))})
MARKUP = st.fixed_dictionaries(
    {"controlPoints": maybe(st.lists(maybe(POINT), max_size=5))},
    optional={"coordinateSystem": maybe(st.sampled_from(["LPS", "RAS", "lps", "IJK"])),
              "carmreg": maybe(st.fixed_dictionaries({"pixel_spacing_mm": maybe(numbers(2))})),
              "type": st.just("Fiducial")})
MRK_DOC = st.fixed_dictionaries({"markups": maybe(st.lists(maybe(MARKUP), max_size=2))},
                                optional={"@schema": st.text(max_size=5)})
PLAIN_DOC = st.one_of(st.dictionaries(LABEL | st.text(max_size=4), maybe(numbers(3) | numbers(2)),
                                      max_size=5),
                      st.lists(maybe(numbers(2)), max_size=5))


@FUZZ
@given(doc=st.one_of(MRK_DOC, PLAIN_DOC, ANY_JSON))
def test_landmark_json_of_any_shape_loads_or_raises_carmreg_error(work, doc):
    target = work / "fuzz.mrk.json"
    target.write_text(json.dumps(doc))
    assert_loads_or_refuses(read_landmarks_3d, target)
    assert_loads_or_refuses(read_landmarks_2d, target)


# ----------------------------------------------------------------------------------------------- regressions

def test_regressions_found_by_fuzzing(tmp_path, seeds):
    """Crashes the fuzzing found once, kept as plain examples (each raised a non-CarmReg exception)."""
    raw = seeds["dicom_xray"].read_bytes()
    sdd_at = raw.index(b"\x18\x00\x10\x11DS") + 8  # value of (0018,1110) DistanceSourceToDetector, "1000"
    (tmp_path / "ds.dcm").write_bytes(raw[:sdd_at] + b"1x00" + raw[sdd_at + 4:])
    with pytest.raises(CarmRegError, match=r"ds.dcm: DICOM DistanceSourceToDetector = '1x00' is not a "):
        load_xray(tmp_path / "ds.dcm")
    (tmp_path / "vr.dcm").write_bytes(raw[:sdd_at - 4] + b"QX" + raw[sdd_at - 2:])  # its VR made unknown
    image = load_xray(tmp_path / "vr.dcm")  # the unreadable element is dropped, named, and asked for
    assert image.intrinsics is None
    assert image.meta["warning_unreadable_elements"] == "(0018,1110) DistanceSourceToDetector"
    with pytest.raises(CarmRegError, match=r"vr.dcm: the source-to-detector distance \(give --sdd-mm.*is not "
                                           r"in the file \(unreadable header elements were ignored: "
                                           r"\(0018,1110\) DistanceSourceToDetector\)"):
        image.require_intrinsics()
    (tmp_path / "big.tif").write_bytes(_tiff_claiming(100_000, 100_000))
    with pytest.raises(CarmRegError, match="big.tif"):
        load_xray(tmp_path / "big.tif")
    (tmp_path / "o.nrrd").write_bytes(b"NRRD0004\ntype: short\ndimension: 3\nsizes: 2 2 2\nencoding: raw\n"
                                      b"endian: little\nspace: left-posterior-superior\n"
                                      b"space directions: (1,0,0) (0,1,0) (0,0,1)\nspace origin: (1,2)\n\n"
                                      + bytes(16))
    with pytest.raises(CarmRegError, match="o.nrrd: NRRD 'space directions' / 'space origin'"):
        load_volume(tmp_path / "o.nrrd")
    (tmp_path / "s.mrk.json").write_text(json.dumps({"markups": [{"carmreg": 5, "controlPoints": [
        {"label": "T12", "position": [1, 2, 0], "carmreg": 3}]}]}))
    assert read_landmarks_2d(tmp_path / "s.mrk.json").labels == ["T12"]


def _tiff_claiming(cols: int, rows: int) -> bytes:
    """A minimal little-endian TIFF header claiming a cols x rows 8-bit grey image (no real data)."""
    entries = [(256, 4, 1, cols), (257, 4, 1, rows), (258, 3, 1, 8), (259, 3, 1, 1), (262, 3, 1, 1),
               (273, 4, 1, 8), (277, 3, 1, 1), (278, 4, 1, rows), (279, 4, 1, min(cols * rows, 2**32 - 1))]
    body = len(entries).to_bytes(2, "little")
    for tag, kind, count, value in entries:
        body += (tag.to_bytes(2, "little") + kind.to_bytes(2, "little") + count.to_bytes(4, "little")
                 + value.to_bytes(4, "little"))
    return b"II*\x00" + (8).to_bytes(4, "little") + body + bytes(4)
