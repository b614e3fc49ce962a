"""Hostile machines and inputs through the real command line (issue 14): bounded, one line, exit code 2.

Every file is made by the test, small; "huge" files are sparse (their size is a header claim or a hole).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from test_cli_errors import assert_one_line_error, register_args, run
from test_cli_errors import case as case  # noqa: F401 - the small valid case (a fixture)

from carmreg.logic.geometry.volume import Volume
from carmreg.logic.io.volumes import write_volume_nrrd

REPO = Path(__file__).resolve().parents[2]


def _small_ct(n: int = 12, spacing_mm: float = 3.0) -> Volume:
    """n^3 voxels: air around a soft-tissue cylinder holding a bone block (a CT by its HU proportions)."""
    affine = np.diag([spacing_mm] * 3 + [1.0])
    ijk = np.indices((n, n, n)).astype(float)
    c = (n - 1) / 2
    hu = np.where((ijk[0] - c) ** 2 + (ijk[1] - c) ** 2 < (0.4 * n) ** 2, 40.0, -1000.0)
    hu[(abs(ijk[0] - c) < n / 8) & (abs(ijk[1] - c) < n / 8)] = 700.0
    return Volume(hu.astype(np.int16), affine, "small")


def _unshare_read_only(root: Path) -> list[str] | None:
    """A command prefix that runs its command with ``root`` mounted read-only (root only), else None."""
    if os.geteuid() != 0 or shutil.which("unshare") is None:
        return None
    probe = subprocess.run(["unshare", "-m", "sh", "-c", f"mount --bind {root} {root} && "
                            f"mount -o remount,ro,bind {root} && ! touch {root}/.probe 2>/dev/null"],
                           capture_output=True)
    if probe.returncode != 0:
        return None
    return ["unshare", "-m", "sh", "-c", f'mount --bind {root} {root} && mount -o remount,ro,bind {root} && '
            'exec "$@"', "sh"]


def test_kernels_run_when_no_cache_folder_is_writable(tmp_path):
    """Neither the install, $HOME/.cache nor $NUMBA_CACHE_DIR writable: the DRR still renders (kernels compiled
    in memory) with a one-line note, exit 0. As root the install is really mounted read-only and HOME /
    NUMBA_CACHE_DIR point under a regular file (mkdir fails even for root); otherwise numba is restricted to
    those two unwritable locators."""
    ct = write_volume_nrrd(tmp_path / "ct.nrrd", _small_ct())
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    env = {**os.environ, "HOME": str(blocker / "home"), "XDG_CACHE_HOME": str(blocker / "cache"),
           "NUMBA_CACHE_DIR": str(blocker / "numba")}
    env.pop("CARMREG_CACHE", None)
    prefix = _unshare_read_only(REPO)
    if prefix is None:
        env["NUMBA_CACHE_LOCATOR_CLASSES"] = "UserProvidedCacheLocator,UserWideCacheLocator"
    out = tmp_path / "drr"
    proc = subprocess.run([*(prefix or []), sys.executable, "-m", "carmreg.cli", "drr", "--ct", str(ct), "--out",
                           str(out), "--size-px", "16", "16"], capture_output=True, text=True, env=env,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    notes = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(notes) == 1 and notes[0].startswith("carmreg: note: no writable cache for compiled kernels")
    assert (tmp_path / "drr.nrrd").stat().st_size > 0


# ------------------------------------------------------------------------ numbers checked before any work

@pytest.mark.parametrize(("replace", "message"), [
    ({"seed": -1}, "--seed -1 is not a valid seed: give a whole number from 0 to 4294967295"),
    ({"seed": 2**32}, "--seed 4294967296 is not a valid seed"),
    ({"frame": -1}, "--frame -1: frames are counted from 0 (the first)"),
])
def test_cli_numbers_are_refused_before_any_work(case, capsys, replace, message):
    code, err = run(capsys, register_args(case, **replace))
    assert_one_line_error(code, err, message)
    assert not (case["folder"] / "out").exists()


def test_empty_out_and_absurd_drr_and_simulate_numbers(case, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, err = run(capsys, ["register", "--ct", str(case["ct"]), "--ct-landmarks", str(case["ct_landmarks"]),
                             "--xray", str(case["xray"]), "--no-clicks", "--out", ""])
    assert_one_line_error(code, err, "--out '' is empty; give the output folder")
    drr = ["drr", "--ct", str(case["ct"]), "--out", str(tmp_path / "d"), "--size-px", "16", "16"]
    code, err = run(capsys, [*drr, "--sdd-mm", "0"])
    assert_one_line_error(code, err, "source-to-detector distance 0.0 mm is not plausible")
    code, err = run(capsys, [*drr, "--sod-mm", "0"])
    assert_one_line_error(code, err, "source-to-isocentre distance 0.0 mm must lie between 0 and")
    code, err = run(capsys, ["simulate", "--out", str(tmp_path / "s"), "--size-px", "0"])
    assert_one_line_error(code, err, "--size-px 0 must be between 64 and 4096")
    code, err = run(capsys, ["register", *register_args(case, out="/proc/carmreg-out")[1:]])
    assert_one_line_error(code, err, "--out /proc/carmreg-out: cannot write there")
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------ garbage is refused

def test_noise_xray_and_all_air_ct_are_refused_before_registering(case, capsys):
    noise = np.random.default_rng(0).integers(0, 65535, case["pixels"].shape, dtype=np.uint16)
    png = case["folder"] / "noise.png"
    Image.fromarray(noise).save(png)
    code, err = run(capsys, register_args(case, xray=png, sdd_mm=1000, pixel_spacing_mm=1.5))
    assert_one_line_error(code, err, "noise.png: the image is noise, not anatomy")
    air = write_volume_nrrd(case["folder"] / "air.nrrd",
                            Volume(np.full((40, 40, 40), -1000, np.int16), np.diag([3.0, 3.0, 3.0, 1.0])))
    code, err = run(capsys, register_args(case, ct=air))
    assert_one_line_error(code, err, "air.nrrd: does not look like a CT of a patient (air 100.00 %")


def test_sigterm_at_any_moment_leaves_no_temporary_files(case, tmp_path):
    """SIGTERM while registering or saving unwinds like Ctrl-C: no hidden temporary file in the cache, no
    staging folder beside the output, the output folder absent or complete."""
    cache, out = tmp_path / "cache", tmp_path / "out"
    argv = [a for a in register_args(case, out=out) if a != "--no-cache"] + ["--cache-dir", str(cache)]
    for delay in (2.0, 4.0):
        proc = subprocess.Popen([sys.executable, "-m", "carmreg.cli", *argv], stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE, text=True)
        try:
            proc.wait(timeout=delay)
        except subprocess.TimeoutExpired:
            proc.terminate()
        _, err = proc.communicate(timeout=120)
        assert "Traceback" not in err
        assert [p.name for p in cache.glob(".*")] == [] if cache.exists() else True
        assert [p.name for p in tmp_path.glob(".out*")] == []
        assert not out.exists() or (out / "carmreg-manifest.json").is_file()


def test_a_full_kernel_cache_costs_a_note_not_a_traceback(tmp_path):
    """$NUMBA_CACHE_DIR on a file system with no space left (a 64 kB tmpfs, filled): the kernel compiles, runs,
    and the failed save is one note line. Needs root (a private mount namespace); skipped otherwise."""
    if os.geteuid() != 0 or shutil.which("unshare") is None:
        pytest.skip("needs root and unshare to mount a full file system")
    full = tmp_path / "full"
    full.mkdir()
    script = tmp_path / "kernel.py"
    script.write_text("from carmreg.logic.jit import njit\n\n\n@njit()\ndef add(a, b):\n    return a + b\n\n\n"
                      "print(add(2, 3))\n")
    shell = (f"mount -t tmpfs -o size=64k tmpfs {full} || exit 77; "
             f"dd if=/dev/zero of={full}/fill bs=4k count=100 2>/dev/null; exec {sys.executable} {script}")
    proc = subprocess.run(["unshare", "-m", "sh", "-c", shell], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "NUMBA_CACHE_DIR": str(full)})
    if proc.returncode == 77:
        pytest.skip("cannot mount a tmpfs here")
    assert proc.returncode == 0 and proc.stdout == "5\n", proc.stderr
    assert proc.stderr.splitlines() == ["carmreg: note: no writable cache for compiled kernels (writing to it "
                                        "failed: No space left on device); they are compiled in memory in every "
                                        "run (about 10 s more; set NUMBA_CACHE_DIR to a writable folder to keep "
                                        "them)"]
