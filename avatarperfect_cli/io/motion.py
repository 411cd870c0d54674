"""SMPL motion files as GART and InstantAvatar use them: .npz with poses (N, 72) and trans (N, 3).

Tools store motions in different world frames: +Y up (SMPL's, GART's), +Z up (AMASS), or the camera's
y-down frame (InstantAvatar's demo motion). `detect_up_axis` reads it from the first frame's root
orientation, and `place_motion` turns a motion upright into a render's world.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import torch

from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.io.atomic import atomic_path
from avatarperfect_cli.io.paths import require_file
from avatarperfect_cli.rotations import axis_angle_to_matrix, matrix_to_axis_angle

# The world up axes a motion may have (--up), as unit vectors in its own world frame.
UP_AXES = {"y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0), "z": (0.0, 0.0, 1.0)}
# Pose widths of other body models, and how to make SMPL's 72 of them: the body is their first 66 columns.
_OTHER_LAYOUTS = {69: "SMPL's joints without the global orientation; put the root's 3 values first",
                  156: "the SMPL-H layout (AMASS); keep its columns 0..65 and add 6 zeros for SMPL's hands",
                  165: "the SMPL-X layout; keep its columns 0..65 and add 6 zeros for SMPL's hands"}  # fmt: skip


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
    if poses.ndim != 2 or poses.shape[1] != 72 or poses.shape[0] == 0:
        layout = _OTHER_LAYOUTS.get(poses.shape[1]) if poses.ndim == 2 and poses.shape[0] else None
        hint = f": {poses.shape[1]} columns is {layout}" if layout else ""
        raise InputFileError(path, f"poses must be (N, 72) with N >= 1, got {poses.shape}{hint}")
    if trans.shape != (poses.shape[0], 3):
        raise InputFileError(path, f"trans must be ({poses.shape[0]}, 3) to match poses, got {trans.shape}")
    if not (np.isfinite(poses).all() and np.isfinite(trans).all()):
        raise InputFileError(path, "poses or trans hold NaN or Inf")
    body_pose = torch.from_numpy(np.ascontiguousarray(poses, dtype=np.float32)).reshape(-1, 24, 3)
    return body_pose, torch.from_numpy(trans.astype(np.float32))


def detect_up_axis(body_pose: torch.Tensor, path: Path) -> str:
    """The key of UP_AXES nearest the first frame's body up (its root orientation applied to SMPL's +Y);
    a one-line error naming `path` when that is an axis no tool uses (then --up must say)."""
    body_up = axis_angle_to_matrix(body_pose[0, 0].double())[:, 1]
    axis = int(body_up.abs().argmax())
    name = ("-" if body_up[axis] < 0 else "") + "xyz"[axis]
    if name not in UP_AXES:
        problem = f"cannot tell which way is up (its first frame's body points along {name}); pass --up y, -y or z"
        raise AvatarPerfectError(f"{path}: {problem}")
    return name


def place_motion(
    body_pose: torch.Tensor,
    transl: torch.Tensor,
    up: str,
    world_up: torch.Tensor,
    toward_camera: torch.Tensor,
    start: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The motion turned into a render's world: upright and facing the camera, starting at `start`.

    body_pose (N, 24, 3), transl (N, 3): the motion in its own world, whose up axis is UP_AXES[up];
    world_up (3,): the render world's up; toward_camera (3,): a direction from the body towards the camera.
    One rotation C takes the motion's up to `world_up` and then turns about it until the first frame's
    body front (SMPL's +Z) faces `toward_camera` seen from above. Root orientations become C R; the root
    path keeps its shape, turned by C: transl'[t] = start + C (transl[t] - transl[0]), so the first frame's
    root lands where `start` puts the render's body.
    Returns body_pose (N, 24, 3) and transl (N, 3), float32.
    """
    world_up = torch.nn.functional.normalize(world_up.double(), dim=0)
    upright = _rotation_between(torch.tensor(UP_AXES[up], dtype=torch.float64), world_up)
    roots = upright @ axis_angle_to_matrix(body_pose[:, 0].double())
    front = _horizontal(roots[0, :, 2], world_up)
    toward = _horizontal(toward_camera.double(), world_up)
    turn = torch.eye(3, dtype=torch.float64)
    if front is not None and toward is not None:
        angle = torch.atan2(torch.dot(torch.linalg.cross(front, toward), world_up), torch.dot(front, toward))
        turn = axis_angle_to_matrix(world_up * angle)
    rotation = turn @ upright
    placed = body_pose.clone().float()
    placed[:, 0] = matrix_to_axis_angle(turn @ roots).float()
    path = (transl.double() - transl[:1].double()) @ rotation.T
    return placed, (path + start.double()).float()


def _horizontal(direction: torch.Tensor, up: torch.Tensor) -> torch.Tensor | None:
    """`direction` (3,) without its component along `up`, normalised; None when it is (nearly) vertical."""
    flat = direction - torch.dot(direction, up) * up
    norm = flat.norm()
    return flat / norm if norm > 1e-6 else None


def _rotation_between(source: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(3, 3) float64 rotation taking unit vector `source` to unit vector `target` by the shortest arc
    (for opposite vectors: half a turn about an axis perpendicular to them)."""
    axis = torch.linalg.cross(source, target)
    sine, cosine = axis.norm(), torch.dot(source, target)
    if sine < 1e-9:
        if cosine > 0:
            return torch.eye(3, dtype=torch.float64)
        helper = torch.eye(3, dtype=torch.float64)[int(source.abs().argmin())]
        axis = torch.nn.functional.normalize(torch.linalg.cross(source, helper), dim=0)
        return axis_angle_to_matrix(axis * torch.pi)
    return axis_angle_to_matrix(axis / sine * torch.atan2(sine, cosine))


def write_motion(path: Path, body_pose: torch.Tensor, transl: torch.Tensor) -> None:
    """Write body_pose (N, 24, 3) and transl (N, 3) as a motion .npz (atomically)."""
    with atomic_path(path) as temporary:
        with open(temporary, "wb") as handle:
            np.savez(handle, poses=body_pose.reshape(-1, 72).numpy().astype(np.float32), trans=transl.numpy().astype(np.float32))
