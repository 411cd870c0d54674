"""SMPL motion files as GART and InstantAvatar use them: .npz with poses (N, 72) and trans (N, 3)."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import torch

from avatarperfect_cli.errors import InputFileError
from avatarperfect_cli.io.atomic import atomic_path
from avatarperfect_cli.io.paths import require_file


def read_motion(path: Path) -> tuple[torch.Tensor, torch.Tensor]:
    """body_pose (N, 24, 3) axis-angle (joint 0 = global orientation) and transl (N, 3), metres."""
    require_file(path)
    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise InputFileError(path, "a single .npy array; a motion is an .npz with poses (N, 72) and trans (N, 3)")
        with data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, ValueError, EOFError, MemoryError, zipfile.BadZipFile) as error:
        raise InputFileError(path, f"not a readable .npz motion ({error})") from None
    for key in ("poses", "trans"):
        if key not in arrays:
            raise InputFileError(path, f"missing '{key}' (a motion has poses (N, 72) and trans (N, 3))")
        if arrays[key].dtype.kind not in "iuf":
            raise InputFileError(path, f"'{key}' holds {arrays[key].dtype} values, not numbers")
    poses, trans = arrays["poses"], arrays["trans"]
    if poses.ndim != 2 or poses.shape[1] < 72 or poses.shape[0] == 0:
        raise InputFileError(path, f"poses must be (N, 72) with N >= 1, got {poses.shape}")
    if trans.shape != (poses.shape[0], 3):
        raise InputFileError(path, f"trans must be ({poses.shape[0]}, 3) to match poses, got {trans.shape}")
    if not (np.isfinite(poses).all() and np.isfinite(trans).all()):
        raise InputFileError(path, "poses or trans hold NaN or Inf")
    body_pose = torch.from_numpy(np.ascontiguousarray(poses[:, :72], dtype=np.float32)).reshape(-1, 24, 3)
    return body_pose, torch.from_numpy(trans.astype(np.float32))


def write_motion(path: Path, body_pose: torch.Tensor, transl: torch.Tensor) -> None:
    """Write body_pose (N, 24, 3) and transl (N, 3) as a motion .npz (atomically)."""
    with atomic_path(path) as temporary:
        with open(temporary, "wb") as handle:
            np.savez(handle, poses=body_pose.reshape(-1, 72).numpy().astype(np.float32), trans=transl.numpy().astype(np.float32))
