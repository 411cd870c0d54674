"""File I/O: atomic writes, 3DGS PLY, camera and pose JSON, images. Bad user files raise InputFileError.

The names below load on first use, so `avatarperfect_cli.io.workspace` (the lock) imports without torch:
the CLI refuses a busy workspace before its heavy imports.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "atomic_path": "atomic",
    "atomic_write_bytes": "atomic",
    "atomic_write_text": "atomic",
    "read_camera": "camera_json",
    "write_camera": "camera_json",
    "read_image": "images",
    "write_image": "images",
    "read_gaussians": "ply",
    "write_gaussians": "ply",
    "PoseFile": "pose_json",
    "read_pose": "pose_json",
    "write_pose": "pose_json",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    globals()[name] = value
    return value
