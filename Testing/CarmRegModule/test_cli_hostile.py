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
