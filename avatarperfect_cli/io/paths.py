"""Checks shared by the readers."""

from __future__ import annotations

from pathlib import Path

from avatarperfect_cli.errors import InputFileError


def require_file(path: Path) -> None:
    """Raise InputFileError unless `path` is an existing regular file."""
    if not path.is_file():
        raise InputFileError(path, "file not found" if not path.exists() else "not a regular file")
