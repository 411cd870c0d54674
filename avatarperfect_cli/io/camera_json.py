"""Camera JSON: {"format": "avatarperfect.camera", "version": 1, "K", "world_to_camera", "width", "height"}."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from avatarperfect_cli.errors import InputFileError
from avatarperfect_cli.io.json_file import (
    get_array,
    get_positive_int,
    read_json_object,
    tensor_to_json,
    write_json_object,
)
from avatarperfect_cli.render.camera import Camera

CAMERA_FORMAT = "avatarperfect.camera"
CAMERA_VERSION = 1
ROTATION_TOLERANCE = 1e-3  # max |R^T R - I| entry accepted for the rotation block of world_to_camera


def camera_from_json(data: dict[str, Any], path: Path, where: str = "") -> Camera:
    """Parse and validate {K, world_to_camera, width, height}; `where` prefixes key names in messages."""
    K = get_array(data, "K", (3, 3), path, where)
    world_to_camera = get_array(data, "world_to_camera", (4, 4), path, where)
    width = get_positive_int(data, "width", path, where)
    height = get_positive_int(data, "height", path, where)
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not torch.equal(K[2], torch.tensor([0.0, 0.0, 1.0], dtype=K.dtype)):
        raise InputFileError(path, f"'{where}K' must have positive focal lengths and last row [0, 0, 1]")
    if not torch.equal(world_to_camera[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=world_to_camera.dtype)):
        raise InputFileError(path, f"'{where}world_to_camera' must have last row [0, 0, 0, 1]")
    rotation = world_to_camera[:3, :3]
    deviation = (rotation.T @ rotation - torch.eye(3, dtype=rotation.dtype)).abs().max().item()
    if deviation > ROTATION_TOLERANCE:
        problem = f"'{where}world_to_camera' 3x3 part is not a rotation (max |R^T R - I| = {deviation:.3g})"
        raise InputFileError(path, problem)
    if torch.linalg.det(rotation) < 0:
        raise InputFileError(path, f"'{where}world_to_camera' 3x3 part is a reflection (determinant < 0)")
    return Camera(K.float(), world_to_camera.float(), width, height)


def camera_to_json(camera: Camera) -> dict[str, Any]:
    """{K, world_to_camera, width, height} as JSON values (float32 precision)."""
    return {
        "K": tensor_to_json(camera.K),
        "world_to_camera": tensor_to_json(camera.world_to_camera),
        "width": int(camera.width),
        "height": int(camera.height),
    }


def read_camera(path: Path | str) -> Camera:
    """Load a camera JSON file (the format/version keys are optional); float32 tensors."""
    path = Path(path)
    return camera_from_json(read_json_object(path, CAMERA_FORMAT, CAMERA_VERSION), path)


def write_camera(path: Path | str, camera: Camera) -> None:
    """Write `camera` as camera JSON, atomically."""
    write_json_object(path, {"format": CAMERA_FORMAT, "version": CAMERA_VERSION, **camera_to_json(camera)})
