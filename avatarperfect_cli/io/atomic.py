"""Atomic file writes: write a temporary file in the target's folder, then rename it onto the target."""

from __future__ import annotations

import ctypes
import errno
import glob
import os
import secrets
import shutil
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

# Test hook: seconds to sleep just before each final rename, so that the kill harness
# (tests/reliability/kill_harness.py) can land signals inside a save. Unset: no delay.
SAVE_DELAY_VARIABLE = "AVATARPERFECT_TEST_SAVE_DELAY"


@contextmanager
def atomic_path(path: Path | str) -> Iterator[Path]:
    """Yield a temporary path next to `path`; on success rename it onto `path`, on any error delete it.

    The temporary name keeps the suffix (`.avatar.tmp-1a2b3c4d.ply` for `avatar.ply`), so writers that infer
    the format from the suffix (Pillow, numpy) work. Missing parent folders are created. Readers never see
    a half-written `path`: it is either the old file or the complete new one.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.stem}.tmp-{secrets.token_hex(4)}{path.suffix}")
    try:
        yield temporary
        _test_save_delay()
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: Path | str, data: bytes) -> None:
    """Write `data` to `path` atomically."""
    with atomic_path(path) as temporary:
        temporary.write_bytes(data)


def atomic_write_text(path: Path | str, text: str, encoding: str = "utf-8") -> None:
    """Write `text` to `path` atomically."""
    with atomic_path(path) as temporary:
        temporary.write_text(text, encoding=encoding)


def staging_dir(target: Path) -> Path:
    """A new, empty hidden folder beside `target`, meant to be renamed onto it once complete.

    It gets the permissions a plain mkdir would give (tempfile's are owner-only).
    """
    target.parent.mkdir(parents=True, exist_ok=True)
    path = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
    umask = os.umask(0)
    os.umask(umask)
    path.chmod(0o777 & ~umask)
    return path


@contextmanager
def atomic_folder(target: Path) -> Iterator[Path]:
    """Yield a new hidden staging folder beside `target`; on success it replaces `target` (see
    `replace_folder`), on any error it is deleted. Readers see the old folder or the complete new one."""
    staging = staging_dir(target)
    try:
        yield staging
        replace_folder(staging, target)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


@contextmanager
def updated_folder(folder: Path) -> Iterator[Path]:
    """Yield a staging copy of `folder` (new or existing) in which to add or replace files; on success it replaces
    `folder` in one step (see `atomic_folder`), so readers see all the changes or none.

    The copy's files are hard links of the originals where the file system has them (hidden files are left
    out): write them only through `atomic_path` and the writers built on it, never in place.
    """
    with atomic_folder(folder) as staging:
        if folder.is_dir():
            shutil.copytree(folder, staging, copy_function=_link_or_copy, ignore=shutil.ignore_patterns(".*"), dirs_exist_ok=True)
        yield staging


def _link_or_copy(source: str, destination: str) -> None:
    try:
        os.link(source, destination)
    except OSError:
        shutil.copy2(source, destination)


def replace_folder(staging: Path, target: Path) -> None:
    """Move the complete folder `staging` onto `target` (which may exist), as one step where possible.

    On Linux an existing `target` is swapped with `staging` by renameat2(RENAME_EXCHANGE), so every
    reader sees the old folder or the new one; the old one, now at `staging`, is then deleted. Where
    that call is missing, the old folder is renamed aside first (`recover_folder` puts it back if a
    crash comes between the two renames).
    """
    _test_save_delay()
    if not target.exists():
        os.replace(staging, target)
        return
    if _exchange(staging, target):
        shutil.rmtree(staging, ignore_errors=True)
        return
    retired = _retired_name(target)
    os.replace(target, retired)
    os.replace(staging, target)
    shutil.rmtree(retired, ignore_errors=True)


def recover_folder(target: Path) -> None:
    """Undo what a crash inside `replace_folder` or `staging_dir` left: put a retired `target` back if
    `target` is missing, and delete the hidden staging folders beside `target`."""
    retired = _retired_name(target)
    if retired.is_dir() and not target.exists():
        os.replace(retired, target)
    for leftover in target.parent.glob(f".{glob.escape(target.name)}.*.tmp*"):
        if leftover.is_dir():
            shutil.rmtree(leftover, ignore_errors=True)


def remove_temporaries(folder: Path) -> None:
    """Delete what killed writers left in `folder` and its subfolders: `atomic_path`'s temporary files and the
    hidden staging folders of `staging_dir` and `replace_folder` (a retired folder whose target is missing is
    put back instead, as `recover_folder` does)."""
    leftovers = list(folder.rglob(".*.tmp*"))
    for leftover in leftovers:
        if leftover.is_dir() and leftover.name.endswith(RETIRED_SUFFIX):
            recover_folder(leftover.with_name(leftover.name[1 : -len(RETIRED_SUFFIX)]))
    for leftover in leftovers:
        if leftover.is_file() and ".tmp-" in leftover.name:
            leftover.unlink(missing_ok=True)
        elif leftover.is_dir() and leftover.name.endswith(".tmp"):
            shutil.rmtree(leftover, ignore_errors=True)


def _test_save_delay() -> None:
    """Sleep $AVATARPERFECT_TEST_SAVE_DELAY seconds when it is set (the only place it is read; see SAVE_DELAY_VARIABLE)."""
    delay = os.environ.get(SAVE_DELAY_VARIABLE)
    if delay:
        time.sleep(float(delay))


RETIRED_SUFFIX = ".retired.tmp"


def _retired_name(target: Path) -> Path:
    return target.with_name(f".{target.name}{RETIRED_SUFFIX}")


_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def _exchange(first: Path, second: Path) -> bool:
    """Atomically swap two paths with Linux's renameat2; False where the system cannot."""
    if not sys.platform.startswith("linux"):
        return False
    renameat2 = getattr(ctypes.CDLL(None, use_errno=True), "renameat2", None)
    if renameat2 is None:
        return False
    if renameat2(_AT_FDCWD, os.fsencode(first), _AT_FDCWD, os.fsencode(second), _RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP):
        return False
    raise OSError(code, os.strerror(code), str(second))
