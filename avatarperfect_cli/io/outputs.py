"""Output paths checked before the work starts, and image pairs written so that both appear or neither.

A stage calls `check_writable_output` / `check_writable_folder` for every path it will write before it
renders or trains, so an unwritable output fails in one line at once instead of after the work.
"""

from __future__ import annotations

import os
import secrets
import shutil
from pathlib import Path

import torch

from avatarperfect_cli.errors import InputFileError
from avatarperfect_cli.io.images import write_image


def check_writable_output(path: Path) -> None:
    """Raise InputFileError unless a file can be written at `path`.

    `path` must not be a folder or another non-regular file, and its folder must exist and be writable,
    or be creatable (its nearest existing ancestor is a writable folder). Nothing is created.
    """
    path = Path(path)
    if path.is_dir():
        raise InputFileError(path, "is a folder; give a file name")
    if path.exists() and not path.is_file():
        raise InputFileError(path, "exists and is not a regular file")
    _check_creatable_under(path, path.parent)


def check_new_output(path: Path, suffixes: tuple[str, ...], force: bool = False) -> None:
    """Raise InputFileError unless a file with one of `suffixes` (".png", ...) can be written at `path`, and, without
    `force`, nothing is there yet: a command never replaces a file it was not asked to."""
    path = Path(path)
    if path.suffix.lower() not in suffixes:
        raise InputFileError(path, f"unknown output type '{path.suffix}'; give a {' or '.join(suffixes)} file name")
    check_writable_output(path)
    if path.exists() and not force:
        raise InputFileError(path, "exists; pass --force to replace it")


def check_output_folder(folder: Path, names: tuple[str, ...], force: bool = False) -> None:
    """Raise InputFileError unless the files `names` can be written in `folder` (existing or creatable) and, without
    `force`, none of them is there yet (other files in the folder are left alone)."""
    check_writable_folder(folder)
    for name in names:
        check_new_output(Path(folder) / name, (Path(name).suffix,), force)


def check_writable_folder(path: Path) -> None:
    """Raise InputFileError unless files can be written in folder `path` (existing, or creatable)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputFileError(path, "exists and is not a folder")
    _check_creatable_under(path, path)


def _check_creatable_under(path: Path, folder: Path) -> None:
    """`folder` exists and is writable, or its nearest existing ancestor is a writable folder."""
    ancestor = folder.absolute()
    while not ancestor.exists() and not ancestor.is_symlink() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise InputFileError(path, f"cannot be written: {ancestor} is not a folder")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise InputFileError(path, f"cannot be written: folder {ancestor} is not writable")


def _temporary_beside(path: Path) -> Path:
    """A hidden, unused name in `path`'s folder that keeps its suffix (writers infer the format from it)."""
    return path.with_name(f".{path.stem}.tmp-{secrets.token_hex(4)}{path.suffix}")


def _keep_copy(path: Path, copy: Path) -> None:
    """Keep `path`'s content at `copy`: a hard link where the file system has them, else a copy."""
    try:
        os.link(path, copy)
    except OSError:
        shutil.copy2(path, copy)


def write_image_pair(path: Path, image: torch.Tensor, second_path: Path, second_image: torch.Tensor) -> None:
    """Write two images (e.g. X.png and X_alpha.png; see `write_image`) so that both appear or neither.

    Both are checked first, written to temporaries beside their targets, then renamed into place; if the
    second rename fails, the first is rolled back (a previous file at `path` is restored). OS errors become
    one-line InputFileErrors naming the file.
    """
    path, second_path = Path(path), Path(second_path)
    check_writable_output(path)
    check_writable_output(second_path)
    staged: list[Path] = []
    previous: Path | None = None
    target = path
    try:
        for target, pixels in ((path, image), (second_path, second_image)):
            staged.append(_temporary_beside(target))
            write_image(staged[-1], pixels)
        target = path
        if path.is_file():
            previous = _temporary_beside(path)
            _keep_copy(path, previous)
        os.replace(staged[0], path)
        target = second_path
        try:
            os.replace(staged[1], second_path)
        except BaseException:
            if previous is not None:
                os.replace(previous, path)
            else:
                path.unlink(missing_ok=True)
            raise
    except OSError as error:
        raise InputFileError(target, f"cannot be written: {error.strerror or error}") from None
    finally:
        for leftover in [*staged, previous]:
            if leftover is not None:
                leftover.unlink(missing_ok=True)

