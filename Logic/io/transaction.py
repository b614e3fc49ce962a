"""A folder written as one transaction: a kill at any moment leaves the old folder or the new one, never a mix.

``FolderTransaction(target)`` gives a staging folder beside the target (``.<name>.carmreg-new-<pid>-<random>``,
same parent, so the same file system). Every file of the new content is written there; on success a manifest
(``carmreg-manifest.json``: every file's size and SHA-256) is written last, the staging folder is fsynced and
swapped with the target in one step:

- Linux: ``renameat2(RENAME_EXCHANGE)`` exchanges the two folders atomically; the old content, now under the
  staging name, is deleted.
- elsewhere: target -> ``.<name>.carmreg-old-<pid>-...``, staging -> target, then the old one is deleted; a kill
  between the two renames leaves the old folder under the hidden name, and the next transaction on that target
  puts it back before anything else.

Files in the target that the previous transaction did not write (listed in its manifest) are the user's own:
they are carried into the new content (hard links, else copies). Any exception (including KeyboardInterrupt and
SystemExit, e.g. from SIGTERM) deletes the staging folder; a SIGKILL leaves it, and the next transaction on the
same target sweeps every staging folder whose process is gone.

When the parent folder cannot be written (the target is an existing writable folder in a read-only parent) or
the target is a mount point (which cannot be renamed),
the files are staged inside the target and moved in one by one, the old manifest removed first and the new one
written last: readers that trust only a complete manifest (``read_manifest``) still never see a mix.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import os
import shutil
import tempfile
from pathlib import Path

from carmreg.logic.errors import CarmRegError
from carmreg.logic.io.atomic import file_sha256

MANIFEST = "carmreg-manifest.json"
_NEW, _OLD = "carmreg-new", "carmreg-old"
_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return True
    return True


def _owner_pid(name: str) -> int | None:
    """The pid in '.<target>.carmreg-new-<pid>-<random>', or None."""
    try:
        return int(name.rsplit("-", 2)[-2])
    except (ValueError, IndexError):
        return None


def _exchange(a: Path, b: Path) -> bool:
    """Atomically exchange two paths (Linux renameat2); False when the platform cannot."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    errno = ctypes.get_errno()
    if errno in (22, 38, 95):  # EINVAL, ENOSYS, EOPNOTSUPP: this file system or kernel cannot exchange
        return False
    raise OSError(errno, os.strerror(errno), str(b))


def _fsync_dir(path: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def read_manifest(folder: str | Path) -> dict | None:
    """The manifest of a folder written by a transaction ({name: {"bytes", "sha256"}}), or None when it is
    missing or unreadable (then the folder's content is not a complete result)."""
    try:
        doc = json.loads((Path(folder) / MANIFEST).read_text(encoding="utf-8"))
        return doc["files"] if isinstance(doc.get("files"), dict) else None
    except (OSError, ValueError, KeyError, AttributeError):
        return None


def sweep_stale(target: str | Path) -> list[Path]:
    """Put back an old folder a kill left between the two renames of the fallback swap; delete the staging
    and old folders of ``target`` whose process is gone. Returns what was removed or restored."""
    target = Path(target)
    parent = target.parent if target.parent.is_dir() else None
    done = []
    places = [p for p in (parent, target if target.is_dir() else None) if p is not None]
    for place in places:
        prefix = f".{target.name}." if place == parent else "."
        for entry in sorted(place.glob(f"{prefix}{_OLD}-*")) + sorted(place.glob(f"{prefix}{_NEW}-*")):
            pid = _owner_pid(entry.name)
            if pid is not None and pid != os.getpid() and _pid_alive(pid):
                continue
            if _OLD in entry.name and place == parent and not target.exists():
                with contextlib.suppress(OSError):
                    os.rename(entry, target)
                    done.append(target)
                    continue
            shutil.rmtree(entry, ignore_errors=True)
            done.append(entry)
    return done


def check_writable_folder(target: str | Path) -> None:
    """Refuse, before any work, an output folder where no transaction can be written (probe: a staging
    folder made and removed in the nearest existing ancestor, or in the target itself)."""
    if str(target).strip() == "":
        raise CarmRegError("--out '' is empty; give the output folder")
    target = Path(target)
    if target.exists() and not target.is_dir():
        raise CarmRegError(f"--out {target} is a file; give a folder for the results")
    places = [next((p for p in target.absolute().parents if p.exists()), Path("/"))]
    if target.is_dir():
        places.insert(0, target)
    errors = []
    for place in places:
        try:
            probe = tempfile.mkdtemp(prefix=f".carmreg-probe-{os.getpid()}-", dir=place)
            os.rmdir(probe)
            return
        except OSError as exc:
            errors.append(f"{place}: {exc.strerror or exc}")
    raise CarmRegError(f"--out {target}: cannot write there ({'; '.join(errors)}); choose another output folder")


class FolderTransaction:
    """``with FolderTransaction(out) as stage: write files into stage`` -> ``out`` holds exactly them (plus
    the user's own files), or, on any failure or kill, exactly what it held before."""

    def __init__(self, target: str | Path, owned_names=()):
        """owned_names: names the writer may produce even when the previous content has no manifest (an old
        result folder): never carried over from it."""
        self.owned = set(owned_names)
        self.target = Path(os.path.realpath(target)) if Path(target).is_symlink() else Path(target)
        self.stage: Path | None = None
        self.in_place = False

    def __enter__(self) -> Path:
        sweep_stale(self.target)
        self.target.parent.mkdir(parents=True, exist_ok=True)
        prefix = f".{self.target.name}.{_NEW}-{os.getpid()}-"
        try:
            if self.target.is_dir() and os.path.ismount(self.target):
                raise PermissionError("a mount point cannot be renamed")
            self.stage = Path(tempfile.mkdtemp(prefix=prefix, dir=self.target.parent))
        except PermissionError:
            if not self.target.is_dir():
                raise
            self.in_place = True
            self.stage = Path(tempfile.mkdtemp(prefix=f".{_NEW}-{os.getpid()}-", dir=self.target))
        os.chmod(self.stage, 0o777 & ~_umask())  # mkdtemp makes 0700; the result gets the user's usual mode
        return self.stage

    def __exit__(self, exc_type, exc, tb) -> bool:
        try:
            if exc_type is None:
                self._commit()
        finally:
            if self.stage is not None and self.stage.exists():
                shutil.rmtree(self.stage, ignore_errors=True)
        return False

    def _written(self) -> dict:
        """{relative posix path: {"bytes", "sha256"}} of every file written into the stage (subfolders too)."""
        files = {}
        for path in sorted(self.stage.rglob("*")):
            name = path.relative_to(self.stage).as_posix()
            if path.is_file() and not path.is_symlink() and name != MANIFEST:
                files[name] = {"bytes": path.stat().st_size, "sha256": file_sha256(path)}
        return files

    def _previous_entries(self) -> set[str]:
        """Top-level names the previous transaction wrote (from its manifest) plus ``owned_names``."""
        return {name.split("/")[0] for name in read_manifest(self.target) or {}} | self.owned

    def _write_manifest(self, folder: Path, files: dict) -> None:
        from carmreg.logic.io.atomic import atomic_write_json

        atomic_write_json(folder / MANIFEST, {"format": "carmreg-manifest/1", "files": files})

    def _carry_over(self, files: dict) -> None:
        """Link the target's entries that are neither new nor written by the previous transaction."""
        if not self.target.is_dir():
            return
        skip = self._previous_entries() | {name.split("/")[0] for name in files} | {MANIFEST}
        for entry in self.target.iterdir():
            name = entry.name
            if name in skip or name.startswith(f".{_NEW}-"):
                continue
            dest = self.stage / name
            if entry.is_dir() and not entry.is_symlink():
                shutil.copytree(entry, dest, symlinks=True, copy_function=_link_or_copy)
            else:
                _link_or_copy(entry, dest)

    def _commit(self) -> None:
        files = self._written()
        if self.in_place:
            self._commit_in_place(files)
            return
        self._carry_over(files)
        self._write_manifest(self.stage, files)
        _fsync_dir(self.stage)
        if not self.target.exists():
            os.rename(self.stage, self.target)
        elif not _exchange(self.stage, self.target):
            old = self.target.parent / f".{self.target.name}.{_OLD}-{os.getpid()}-{os.urandom(4).hex()}"
            os.rename(self.target, old)
            os.rename(self.stage, self.target)
            shutil.rmtree(old, ignore_errors=True)
        _fsync_dir(self.target.parent)

    def _commit_in_place(self, files: dict) -> None:
        """Old manifest out first, the new entries moved in one by one, the new manifest last."""
        previous = self._previous_entries()
        (self.target / MANIFEST).unlink(missing_ok=True)
        new = {name.split("/")[0] for name in files}
        for name in previous | new:
            old = self.target / name
            if name in (".", "..", "") or "/" in name or not (old.exists() or old.is_symlink()):
                continue
            if old.is_dir() and not old.is_symlink():
                shutil.rmtree(old)
            elif name not in new:
                old.unlink()
        for name in sorted(new):
            os.replace(self.stage / name, self.target / name)
        self._write_manifest(self.target, files)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _link_or_copy(src, dst) -> None:
    try:
        os.link(src, dst, follow_symlinks=False)
    except OSError:
        shutil.copy2(src, dst, follow_symlinks=False)
