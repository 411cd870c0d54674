"""Pose JSON: {"format": "avatarperfect.pose", "version": 1, "body_pose", "transl", "camera": {...}}."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from avatarperfect_cli.errors import InputFileError
from avatarperfect_cli.io.camera_json import camera_from_json, camera_to_json
from avatarperfect_cli.io.json_file import get_array, get_key, read_json_object, tensor_to_json, write_json_object
from avatarperfect_cli.render.camera import Camera

POSE_FORMAT = "avatarperfect.pose"
POSE_VERSION = 1
NUM_JOINTS = 24


@dataclass
class PoseFile:
    """A body pose seen from a camera.

    body_pose: (24, 3) SMPL axis-angle per joint, radians; joint 0 is the global orientation
    transl:    (3,) body translation, metres, world frame
    camera:    the camera that views the posed body
    """

    body_pose: torch.Tensor
    transl: torch.Tensor
    camera: Camera

    def __post_init__(self) -> None:
        if tuple(self.body_pose.shape) != (NUM_JOINTS, 3):
            raise ValueError(f"body_pose has shape {tuple(self.body_pose.shape)}, expected ({NUM_JOINTS}, 3)")
        if tuple(self.transl.shape) != (3,):
            raise ValueError(f"transl has shape {tuple(self.transl.shape)}, expected (3,)")


def read_pose(path: Path | str) -> PoseFile:
    """Load a pose JSON file (the format/version keys are optional); float32 tensors."""
    path = Path(path)
    data = read_json_object(path, POSE_FORMAT, POSE_VERSION)
    body_pose = get_array(data, "body_pose", (NUM_JOINTS, 3), path)
    transl = get_array(data, "transl", (3,), path)
    camera = get_key(data, "camera", path)
    if not isinstance(camera, dict):
        raise InputFileError(path, "'camera' must be a JSON object with K, world_to_camera, width and height")
    return PoseFile(body_pose.float(), transl.float(), camera_from_json(camera, path, where="camera."))


def write_pose(path: Path | str, pose: PoseFile) -> None:
    """Write `pose` as pose JSON, atomically."""
    write_json_object(
        path,
        {
            "format": POSE_FORMAT,
            "version": POSE_VERSION,
            "body_pose": tensor_to_json(pose.body_pose),
            "transl": tensor_to_json(pose.transl),
            "camera": camera_to_json(pose.camera),
        },
    )
