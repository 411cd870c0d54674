"""Camera JSON: {"format": "avatarperfect.camera", "version": 1, "K", "world_to_camera", "width", "height"}."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
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
LAST_ROW_TOLERANCE = 1e-6  # max deviation of K's and world_to_camera's last rows from [0, 0, (0,) 1]
MAX_IMAGE_SIDE_VARIABLE = "AVATARPERFECT_MAX_IMAGE_SIDE"
DEFAULT_MAX_IMAGE_SIDE = 8192  # pixels; an RGB float32 frame of 8192^2 already takes 800 MB


def max_image_side() -> int:
    """The largest camera width or height accepted, pixels: $AVATARPERFECT_MAX_IMAGE_SIDE, else 8192."""
    text = os.environ.get(MAX_IMAGE_SIDE_VARIABLE, "").strip()
    if not text:
        return DEFAULT_MAX_IMAGE_SIDE
    if not text.isdigit() or int(text) < 1:
        raise AvatarPerfectError(f"{MAX_IMAGE_SIDE_VARIABLE}={text!r} is not a positive integer number of pixels")
    return int(text)


def check_camera_values(
    K: torch.Tensor, world_to_camera: torch.Tensor, width: int, height: int, path: Path, names: tuple[str, str]
) -> None:
    """Raise InputFileError(path, ...) unless the camera is usable.

    K (3, 3) and world_to_camera (4, 4) are finite float64 pixels / metres; names are the two matrices'
    names in the file, for the messages. K needs positive focal lengths and last row [0, 0, 1];
    world_to_camera must be rigid (a rotation, not a reflection, and last row [0, 0, 0, 1]); both must fit
    float32; width and height must not exceed `max_image_side()`.
    """
    k_name, view_name = names
    if K[0, 0] <= 0 or K[1, 1] <= 0 or (K[2] - K.new_tensor([0.0, 0.0, 1.0])).abs().max() > LAST_ROW_TOLERANCE:
        raise InputFileError(path, f"{k_name} must have positive focal lengths and last row [0, 0, 1]")
    if (world_to_camera[3] - world_to_camera.new_tensor([0.0, 0.0, 0.0, 1.0])).abs().max() > LAST_ROW_TOLERANCE:
        raise InputFileError(path, f"{view_name} must have last row [0, 0, 0, 1]")
    rotation = world_to_camera[:3, :3]
    deviation = (rotation.T @ rotation - torch.eye(3, dtype=rotation.dtype)).abs().max().item()
    if deviation > ROTATION_TOLERANCE:
        problem = f"{view_name} 3x3 part is not a rotation (max |R^T R - I| = {deviation:.3g}): not a rigid transform"
        raise InputFileError(path, problem)
    if torch.linalg.det(rotation) < 0:
        raise InputFileError(path, f"{view_name} 3x3 part is a reflection (determinant < 0): not a rigid transform")
    for name, matrix in ((k_name, K), (view_name, world_to_camera)):
        if not torch.isfinite(matrix.float()).all():
            raise InputFileError(path, f"{name} holds values too large for float32")
    limit = max_image_side()
    if max(width, height) > limit:
        raise InputFileError(
            path,
            f"image size {width}x{height} exceeds the maximum side of {limit} px "
            f"(set {MAX_IMAGE_SIDE_VARIABLE} to allow larger images)",
        )


def camera_from_json(data: dict[str, Any], path: Path, where: str = "") -> Camera:
    """Parse and validate {K, world_to_camera, width, height} (see `check_camera_values`); `where` prefixes key
    names in messages."""
    K = get_array(data, "K", (3, 3), path, where)
    world_to_camera = get_array(data, "world_to_camera", (4, 4), path, where)
    width = get_positive_int(data, "width", path, where)
    height = get_positive_int(data, "height", path, where)
    check_camera_values(K, world_to_camera, width, height, path, (f"'{where}K'", f"'{where}world_to_camera'"))
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
