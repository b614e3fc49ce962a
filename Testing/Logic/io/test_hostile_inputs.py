"""Hostile files and interrupted saves (issue 14): bounded reads, budgets before allocating, one transaction.

Every file is made by the test and small; the "huge" ones are sparse (a hole, or a header claim) or a few kB of
gzip that would inflate to tens of MB. Memory is measured with tracemalloc (numpy allocations are traced).
"""

from __future__ import annotations

import gzip
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
import tracemalloc
import zlib
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pydicom
import pytest

from carmreg.logic.errors import CarmRegError, GeometryError, InputFileError, RegistrationError, quote
from carmreg.logic.geometry.camera import CarmIntrinsics
from carmreg.logic.geometry.volume import Volume
from carmreg.logic.io import array_cache
from carmreg.logic.io.array_cache import sweep_cache
from carmreg.logic.io.landmarks import read_landmarks_2d, read_landmarks_3d
from carmreg.logic.io.session import load_session
from carmreg.logic.io.transaction import MANIFEST, FolderTransaction, check_writable_folder, read_manifest
from carmreg.logic.io.volumes import load_volume, write_dicom_series, write_volume_nrrd
from carmreg.logic.io.xray import load_xray, write_xray_dicom
from carmreg.logic.registration.database import build_database, check_database_size
from carmreg.logic.registration.sanity import check_ct_content, check_xray_content

MiB = 1024**2


@contextmanager
def bounded(seconds: int = 10, peak_bytes: int = 50 * MiB):
    """Fail on a hang (SIGALRM) or on more than ``peak_bytes`` traced allocations inside the block."""
    def alarm(signum, frame):
        raise TimeoutError(f"no answer within {seconds} s")

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(seconds)
    tracemalloc.start()
    try:
        yield
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    assert peak < peak_bytes, f"peak {peak / MiB:.0f} MiB"


def _ct(n: int = 12, spacing_mm: float = 3.0) -> Volume:
    """Air, a soft-tissue cylinder and a bone block: passes the CT content check."""
    ijk = np.indices((n, n, n)).astype(float)
    c = (n - 1) / 2
    hu = np.where((ijk[0] - c) ** 2 + (ijk[1] - c) ** 2 < (0.4 * n) ** 2, 40.0, -1000.0)
    hu[(abs(ijk[0] - c) < n / 8) & (abs(ijk[1] - c) < n / 8)] = 700.0
    return Volume(hu.astype(np.int16), np.diag([spacing_mm] * 3 + [1.0]), "ct")


def _nrrd_header(sizes=(8, 8, 8), encoding="gzip", extra="") -> bytes:
    return (f"NRRD0004\ntype: short\ndimension: 3\nspace: left-posterior-superior\nsizes: "
            f"{' '.join(map(str, sizes))}\nspace directions: (1,0,0) (0,1,0) (0,0,1)\nendian: little\n"
            f"encoding: {encoding}\nspace origin: (0,0,0)\n{extra}\n").encode()


# ------------------------------------------------------------------------------------ decompression bombs

def test_gzip_nrrd_bomb_is_refused_after_one_chunk(tmp_path):
    """Header 8x8x8 int16 (1 kB), gzip payload inflating to 64 MiB: refused, < 50 MiB traced, < 10 s."""
    path = tmp_path / "bomb.nrrd"
    path.write_bytes(_nrrd_header() + gzip.compress(bytes(64 * MiB), 9))
    assert path.stat().st_size < 200_000
    with bounded(), pytest.raises(InputFileError, match=r"bomb.nrrd: the compressed NRRD voxel data inflate "
                                  r"to more than the 1024 bytes"):
        load_volume(path)


def test_metaimage_compressed_bomb_and_trailing_bytes(tmp_path):
    """CompressedData inflating to 64 MiB is refused; a LOCAL file with 3 GiB of trailing bytes (a sparse
    hole) reads only the 12^3 voxels its header announces."""
    ct = _ct()
    head = ("ObjectType = Image\nNDims = 3\nDimSize = 12 12 12\nElementSpacing = 3 3 3\nOffset = 0 0 0\n"
            "ElementType = MET_SHORT\n")
    bomb = tmp_path / "bomb.mha"
    bomb.write_bytes((head + "CompressedData = True\nElementDataFile = LOCAL\n").encode()
                     + zlib.compress(bytes(64 * MiB), 9))
    with bounded(), pytest.raises(InputFileError, match="bomb.mha: the compressed MetaImage voxel data inflate "
                                  "to more than the 3456 bytes"):
        load_volume(bomb)
    tail = tmp_path / "tail.mha"
    tail.write_bytes((head + "ElementDataFile = LOCAL\n").encode() + ct.hu.tobytes(order="F"))
    with open(tail, "r+b") as handle:
        handle.truncate(3 * 1024**3)  # sparse: no disk space used
    with bounded():
        loaded = load_volume(tail)
    assert np.array_equal(loaded.hu, ct.hu)


def test_a_header_announcing_gigabytes_over_a_tiny_payload_is_refused_before_allocating(tmp_path):
    """A legal-size header (1000^3 int16 = 2 GB, under the 8 GiB limit) over 1 kB of voxels: refused as
    truncated before any buffer of the announced size exists (raw NRRD, MetaImage LOCAL, .nii, .nii.gz)."""
    import nibabel as nib

    sizes = (1000, 1000, 1000)
    raw = tmp_path / "big.nrrd"
    raw.write_bytes(_nrrd_header(sizes, "raw") + bytes(1024))
    mha = tmp_path / "big.mha"
    mha.write_bytes(b"ObjectType = Image\nNDims = 3\nDimSize = 1000 1000 1000\nElementSpacing = 0.5 0.5 0.5\n"
                    b"Offset = 0 0 0\nElementType = MET_SHORT\nElementDataFile = LOCAL\n" + bytes(1024))
    header = nib.Nifti1Image(np.zeros((2, 2, 2), np.int16), np.eye(4)).header.copy()
    header.set_data_shape(sizes)
    nii = tmp_path / "big.nii"
    with open(nii, "wb") as handle:
        header.write_to(handle)
        handle.write(bytes(int(header["vox_offset"]) - handle.tell() + 1024))
    niigz = tmp_path / "big.nii.gz"
    niigz.write_bytes(gzip.compress(nii.read_bytes()))
    for path in (raw, mha, nii, niigz):
        with bounded(), pytest.raises(InputFileError, match=rf"{path.name}: .*(holds|inflates to) \d+ bytes.* "
                                      r"header needs \d+.*truncated"):
            load_volume(path)


# ------------------------------------------------------------------------------ regular files only, no hang

def test_pipes_devices_and_symlink_loops_never_hang(tmp_path):
    """A CT, X-ray, landmark or session file that is a named pipe, a .nhdr whose data file is a pipe: one
    line naming it; a series folder holding a pipe, a link to /dev/zero and a symlink loop: the slices load."""
    pipe = tmp_path / "pipe.nrrd"
    os.mkfifo(pipe)
    nhdr = tmp_path / "ct.nhdr"
    nhdr.write_bytes(_nrrd_header(encoding="raw", extra="data file: pipe.nrrd\n"))
    series = tmp_path / "series"
    write_dicom_series(series, _ct(n=6))
    os.mkfifo(series / "fifo.dcm")
    (series / "zero.dcm").symlink_to("/dev/zero")
    (series / "loop.dcm").symlink_to(series / "loop.dcm")
    with bounded():
        with pytest.raises(InputFileError, match=r"pipe.nrrd: CT is a named pipe, not a regular file"):
            load_volume(pipe)
        with pytest.raises(InputFileError, match=r"pipe.nrrd: NRRD data file \(named in ct.nhdr\) is a named "
                           "pipe"):
            load_volume(nhdr)
        with pytest.raises(InputFileError, match="X-ray file is a named pipe"):
            load_xray(pipe)
        with pytest.raises(InputFileError, match="landmark file is a named pipe"):
            read_landmarks_3d(pipe)
        with pytest.raises(InputFileError, match="session file is a named pipe"):
            load_session(pipe)
        with pytest.raises(InputFileError, match="is a folder; give the landmark file"):
            read_landmarks_2d(tmp_path)
        assert load_volume(series).shape == (6, 6, 6)


# --------------------------------------------------------------------------------- budgets before allocating

def test_ct_whose_spacing_is_not_in_mm_is_refused(tmp_path):
    """Spacing x1000 (um written as mm): refused at load, before any level is resampled."""
    path = write_volume_nrrd(tmp_path / "um.nrrd", _ct(spacing_mm=3000.0))
    with bounded(), pytest.raises(InputFileError, match=r"um.nrrd: the CT spans 36000 x 36000 x 36000 mm .* "
                                  "not in mm"):
        load_volume(path)


def test_detector_larger_than_any_carm_is_refused(tmp_path):
    """ImagerPixelSpacing 2.5 on 1024 px = a 2.56 m detector: refused, naming the tag; --pixel-spacing-mm too."""
    pixels = np.tile(np.linspace(100, 4000, 64, dtype=np.uint16), (64, 1))
    path = write_xray_dicom(tmp_path / "xa.dcm", pixels, CarmIntrinsics(1000.0, (0.3, 0.3), (64, 64)))
    ds = pydicom.dcmread(path)
    ds.Rows = ds.Columns = 1024
    ds.PixelData = np.tile(np.arange(1024, dtype=np.uint16), (1024, 1)).tobytes()
    ds.ImagerPixelSpacing = [2.5, 2.5]
    ds.save_as(path)
    with pytest.raises(GeometryError, match=r"xa.dcm: pixel spacing \(2.5, 2.5\) mm makes the 1024x1024 px "
                       r"detector 2560 x 2560 mm, larger than any C-arm detector .*ImagerPixelSpacing"):
        load_xray(path)
    with pytest.raises(GeometryError, match="2560 x 2560 mm"):
        load_xray(path, pixel_spacing_mm=2.5)
    assert load_xray(path, pixel_spacing_mm=0.25).intrinsics.pixel_spacing_mm == (0.25, 0.25)
    with pytest.raises(GeometryError, match=r"xa.dcm: pixel spacing \(0.1, 0.31\) mm: columns and rows differ by "
                       r"3.1x"):
        load_xray(path, pixel_spacing_mm=(0.1, 0.31))


def test_database_budget_is_checked_before_allocating():
    with pytest.raises(RegistrationError, match=r"would hold 100000 DRRs of 128x128 px \(6.1 GiB, limit 1 GiB\)"):
        check_database_size(100_000, (128, 128))
    check_database_size(2601, (64, 64))


# ---------------------------------------------------------------------------------------------- DRR cache

def test_cache_damaged_with_finite_values_or_replaced_by_a_pipe_is_rebuilt(tmp_path, tiny_db_inputs):
    inputs = tiny_db_inputs
    first = build_database(*inputs, 0.0, tmp_path)
    data = tmp_path / f"db-{first.key}.npy"
    reference = np.array(first.drrs)
    damaged = np.load(data)
    damaged[0, 0] += 0.5  # finite, plausible, wrong
    with open(data, "r+b") as handle:  # in place, same size: only the checksum can tell
        handle.seek(os.path.getsize(data) - damaged.nbytes)
        handle.write(damaged.tobytes())
    again = build_database(*inputs, 0.0, tmp_path)
    assert not again.from_cache and np.array_equal(again.drrs, reference)
    assert build_database(*inputs, 0.0, tmp_path).from_cache
    data.unlink()
    os.mkfifo(data)
    with bounded():
        piped = build_database(*inputs, 0.0, tmp_path)
    assert not piped.from_cache and np.array_equal(piped.drrs, reference)


def test_cache_is_capped_and_stale_temporary_files_are_swept(tmp_path, monkeypatch):
    """Temp files older than 15 min go; least recently used databases go beyond the cap."""
    stale, fresh = tmp_path / ".db-abc.x1.npy", tmp_path / ".db-def.x2.npy"
    for path in (stale, fresh):
        path.write_bytes(b"x" * 10)
    old = time.time() - 3600
    os.utime(stale, (old, old))
    dbs = []
    for i in range(3):
        data = tmp_path / f"db-{i}.npy"
        data.write_bytes(b"0" * 1000)
        data.with_suffix(".json").write_text("{}")
        os.utime(data, (old + i, old + i))
        dbs.append(data)
    monkeypatch.setattr(array_cache, "MAX_CACHE_BYTES", 2500)
    deleted = sweep_cache(tmp_path, room_bytes=1000)
    assert stale in deleted and fresh.exists()
    assert [p.exists() for p in dbs] == [False, False, True]


# ------------------------------------------------------------------------------------- result transaction

def _write_version(stage: Path, version: int, n_files: int = 4) -> None:
    for k in range(n_files):
        (stage / f"f{k}.txt").write_text(f"{version}\n" * 2000)


def test_transaction_failure_leaves_the_old_folder_and_keeps_user_files(tmp_path):
    out = tmp_path / "out"
    with FolderTransaction(out) as stage:
        _write_version(stage, 1, n_files=5)
    umask = os.umask(0)
    os.umask(umask)
    assert out.stat().st_mode & 0o777 == 0o777 & ~umask  # the user's usual mode, not mkdtemp's 0700
    (out / "my-notes.txt").write_text("mine")
    with pytest.raises(RuntimeError), FolderTransaction(out) as stage:
        _write_version(stage, 2)
        raise RuntimeError("disk full")
    assert {p.read_text().split()[0] for p in out.glob("f*.txt")} == {"1"} and len(list(out.glob("f*"))) == 5
    with FolderTransaction(out) as stage:
        _write_version(stage, 3, n_files=3)
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "f0.txt", "f1.txt", "f2.txt", "my-notes.txt"]
    assert set(read_manifest(out)) == {"f0.txt", "f1.txt", "f2.txt"}
    assert not list(tmp_path.glob(".out.*"))


KILL_LOOP = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from carmreg.logic.io.transaction import FolderTransaction
    out, version = Path(sys.argv[1]), 0
    while True:
        version += 1
        with FolderTransaction(out) as stage:
            for k in range(6):
                (stage / f"f{k}.txt").write_text(f"{version}\\n" * 20000)
""")


def test_sigkill_at_any_moment_leaves_the_old_folder_or_the_new_one(tmp_path):
    """A process saving in a loop is killed (SIGKILL) 8 times at different moments: the folder always holds
    one version in every file, matching its manifest; the next save sweeps what the kill left."""
    out = tmp_path / "out"
    script = tmp_path / "loop.py"
    script.write_text(KILL_LOOP)
    rng = np.random.default_rng(3)
    for _ in range(8):
        proc = subprocess.Popen([sys.executable, str(script), str(out)])
        time.sleep(0.6 + rng.uniform(0, 0.4))
        proc.kill()
        proc.wait()
        files = sorted(out.glob("f*.txt"))
        assert len(files) == 6
        assert len({f.read_text() for f in files}) == 1
        manifest = read_manifest(out)
        assert manifest is not None and sorted(manifest) == [f.name for f in files]
    with FolderTransaction(out) as stage:
        _write_version(stage, 0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["loop.py", "out"]


def test_unwritable_output_is_refused_before_any_work(tmp_path):
    with pytest.raises(CarmRegError, match=r"--out /proc/carmreg-out: cannot write there"):
        check_writable_folder("/proc/carmreg-out")
    with pytest.raises(CarmRegError, match="--out '' is empty"):
        check_writable_folder("")
    check_writable_folder(tmp_path / "new" / "deeper")


# -------------------------------------------------------------------------------------------- landmarks

def _json(tmp_path: Path, name: str, doc) -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(doc) if not isinstance(doc, str) else doc)
    return path


def test_landmark_values_are_never_reinterpreted(tmp_path):
    with pytest.raises(InputFileError, match=r"uvz.json: unnamed click 1 \[100, 80, 0\] is not 2 numbers"):
        read_landmarks_2d(_json(tmp_path, "uvz.json", [[100, 80, 0], [100, 120, 0], [100, 160, 0],
                                                        [100, 200, 0]]))
    with pytest.raises(InputFileError, match=r"bool.json: the position of 'T12' \[true, 0, 0\] is not 3 numbers"):
        read_landmarks_3d(_json(tmp_path, "bool.json", {"T12": [True, 0, 0], "L1": [0, 0, 30]}))
    with pytest.raises(InputFileError, match="deep.json: the JSON is nested too deeply"):
        read_landmarks_3d(_json(tmp_path, "deep.json", "[" * 100_000 + "]" * 100_000))
    with pytest.raises(InputFileError, match="th12.json: landmark label 'Th12' is not a vertebral level"):
        read_landmarks_3d(_json(tmp_path, "th12.json", {"Th12": [0, 0, 0], "Th11": [0, 0, 30]}))
    huge = "T" + "x" * 10 * MiB
    with pytest.raises(CarmRegError) as info:
        read_landmarks_3d(_json(tmp_path, "huge.json", {huge: [0, 0, 0]}))
    assert len(str(info.value)) < 400 and "10485761 characters" in str(info.value)
    assert quote("abc") == "'abc'"


# ---------------------------------------------------------------------------------------------- sessions

@pytest.mark.parametrize(("change", "message"), [
    ({"geometry_overrides": {"sdd_mm": "abc"}}, "geometry override sdd_mm = 'abc' is not a positive number"),
    ({"version": "abc"}, "session \"version\" 'abc' is not a whole number"),
    ({"data": [1, 2]}, "\"data\" \\[1, 2\\] is not an object"),
    ({"landmarks": {"xray": [{"label": "T12", "uv_px": [True, 3]}]}}, "X-ray landmark 1 needs \"uv_px\""),
    ({"landmarks": {"ct": [{"label": 12, "position_lps_mm": [1, 2, 3]}]}}, "CT landmark 1 label 12 is not a name"),
])
def test_bad_session_fields_are_named(tmp_path, change, message):
    doc = {"format": "carmreg-session", "version": 1, "data": {}, "landmarks": {}, **change}
    with pytest.raises(InputFileError, match=message):
        load_session(_json(tmp_path, "s.carmreg.json", doc))


def test_deeply_nested_session_is_refused(tmp_path):
    with pytest.raises(InputFileError, match="not a readable session file"):
        load_session(_json(tmp_path, "deep.carmreg.json", '{"format": ' + "[" * 100_000 + "]" * 100_000 + "}"))


# --------------------------------------------------------------------------------------- content sanity

def test_ct_content_must_look_like_a_ct():
    ct = _ct(n=16)
    fractions = check_ct_content(ct.hu, "ct.nrrd")
    assert fractions["bone"] > 0.01 and fractions["soft_tissue"] > 0.2
    with pytest.raises(InputFileError, match=r"air.nrrd: does not look like a CT of a patient \(air 100.00 %"):
        check_ct_content(np.full((16, 16, 16), -1000, np.int16), "air.nrrd")
    block = ct.hu.astype(np.float32)
    block[:4, :4, :4] = 3e38
    with pytest.raises(InputFileError, match=r"block.nrrd: voxel values reach -1000 .. 3e\+38"):
        check_ct_content(block, "block.nrrd")


def test_xray_content_must_look_like_an_xray():
    rows, cols = np.mgrid[0:128, 0:128]
    anatomy = 2000 + 800 * np.exp(-((cols - 64) / 15.0) ** 2) * (1 + 0.3 * np.sin(rows / 9.0))
    assert check_xray_content(anatomy, "xa.dcm") > 0.9
    noise = np.random.default_rng(0).uniform(0, 4000, (128, 128))
    with pytest.raises(InputFileError, match=r"noise.png: the image is noise, not anatomy \(correlation of "
                       r"neighbouring 4x4-pixel blocks -?0.0"):
        check_xray_content(noise, "noise.png")
    with pytest.raises(InputFileError, match=r"neg.tif: every pixel is <= 0 \(maximum -1.6"):
        check_xray_content(-anatomy / anatomy.max() - 1, "neg.tif")


def test_xray_dicom_modality_lut_is_applied(tmp_path):
    pixels = np.tile(np.arange(100, 164, dtype=np.uint16), (64, 1))
    path = write_xray_dicom(tmp_path / "lut.dcm", pixels, CarmIntrinsics(1000.0, (0.3, 0.3), (64, 64)))
    ds = pydicom.dcmread(path)
    ds.RescaleSlope, ds.RescaleIntercept = "2", "-150"
    ds.save_as(path)
    xray = load_xray(path)
    assert np.array_equal(xray.pixels, 2.0 * pixels - 150.0)
    assert xray.meta["modality_lut"] == {"slope": 2.0, "intercept": -150.0}
    with pytest.raises(InputFileError, match=r"lut.dcm: --frame -1: frames are counted from 0"):
        load_xray(path, frame=-1)


def test_full_disk_during_save_result_is_one_line_and_keeps_the_old_result(tmp_path, monkeypatch):
    import errno

    from carmreg.logic.report import result_files

    out = tmp_path / "out"
    with FolderTransaction(out, owned_names=result_files.RESULT_FILES) as stage:
        (stage / "result.json").write_text('{"ok": true, "old": 1}')

    def full_disk(result, stage, *args):
        (stage / "result.json").write_text('{"ok": true, "new": 1}')
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(result_files, "_write_result_files", full_disk)
    with pytest.raises(CarmRegError, match=r"out: could not write the results \(No space left on device\); the "
                       "folder still holds its previous content"):
        result_files.save_result(None, out, None)
    assert json.loads((out / "result.json").read_text()) == {"ok": True, "old": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_dicom_far_larger_than_its_pixels_is_refused_before_reading(tmp_path):
    """An X-ray and a CT slice followed by a 3 GiB hole: refused from the file size, nothing read."""
    pixels = np.tile(np.arange(100, 164, dtype=np.uint16), (64, 1))
    xa = write_xray_dicom(tmp_path / "xa.dcm", pixels, CarmIntrinsics(1000.0, (0.3, 0.3), (64, 64)))
    series = write_dicom_series(tmp_path / "s", _ct(n=6))
    for path in (xa, series[2]):
        with open(path, "r+b") as handle:
            handle.truncate(3 * 1024**3)
    with bounded():
        with pytest.raises(InputFileError, match=r"xa.dcm: the file holds 3072 MB, far more than its 64 x 64 px x "
                           r"1 frame\(s\) image needs \(0.0 MB\)"):
            load_xray(xa)
        with pytest.raises(InputFileError, match=r"slice_0002.dcm: the file holds 3072 MB, far more than its 6 x 6"):
            load_volume(tmp_path / "s")


def test_a_mount_point_as_output_is_written_in_place_behind_its_manifest(tmp_path):
    """A result folder that is a mount point cannot be swapped: its files are replaced one by one, the old
    manifest removed first and the new one written last (root only: a private mount namespace)."""
    if os.geteuid() != 0 or shutil.which("unshare") is None:
        pytest.skip("needs root and unshare to mount a file system")
    out = tmp_path / "usb"
    out.mkdir()
    script = tmp_path / "save.py"
    script.write_text(textwrap.dedent(f"""
        from pathlib import Path
        from carmreg.logic.io.transaction import FolderTransaction, read_manifest
        out = Path({str(out)!r})
        for version in (1, 2):
            with FolderTransaction(out, owned_names=["old.txt"]) as stage:
                (stage / f"v{{version}}.txt").write_text(str(version))
        print(sorted(p.name for p in out.iterdir()), sorted(read_manifest(out)))
    """))
    proc = subprocess.run(["unshare", "-m", "sh", "-c", f"mount -t tmpfs tmpfs {out} || exit 77; "
                           f"echo old > {out}/old.txt; echo mine > {out}/mine.txt; exec {sys.executable} {script}"],
                          capture_output=True, text=True, timeout=120)
    if proc.returncode == 77:
        pytest.skip("cannot mount a tmpfs here")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "['carmreg-manifest.json', 'mine.txt', 'v2.txt'] ['v2.txt']"


def test_subfolders_written_by_a_transaction_are_part_of_it(tmp_path):
    """A scene folder written beside the result is named in the manifest and replaced whole; an old one the
    new result does not write is removed, never mixed in."""
    out = tmp_path / "out"
    with FolderTransaction(out) as stage:
        (stage / "scene").mkdir()
        (stage / "scene" / "a.mrml").write_text("1")
        (stage / "scene" / "old.nrrd").write_text("1")
    assert set(read_manifest(out)) == {"scene/a.mrml", "scene/old.nrrd"}
    with FolderTransaction(out) as stage:
        (stage / "scene").mkdir()
        (stage / "scene" / "a.mrml").write_text("2")
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == [MANIFEST, "scene", "scene/a.mrml"]
    with FolderTransaction(out) as stage:
        (stage / "result.json").write_text("3")
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "result.json"]
