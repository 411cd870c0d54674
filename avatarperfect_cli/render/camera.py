"""Pinhole camera in the OpenCV convention (x right, y down, z forward)."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Camera:
    """A pinhole camera.

    K:               (3, 3) intrinsics in pixels; pixel centres sit at +0.5
    world_to_camera: (4, 4) rigid transform, world frame -> OpenCV camera frame
    width, height:   image size in pixels
    """

    K: torch.Tensor
    world_to_camera: torch.Tensor
    width: int
    height: int

    def __post_init__(self) -> None:
        if tuple(self.K.shape) != (3, 3):
            raise ValueError(f"K has shape {tuple(self.K.shape)}, expected (3, 3)")
        if tuple(self.world_to_camera.shape) != (4, 4):
            raise ValueError(f"world_to_camera has shape {tuple(self.world_to_camera.shape)}, expected (4, 4)")
        if self.width < 1 or self.height < 1:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")

    @property
    def center(self) -> torch.Tensor:
        """(3,) camera centre in the world frame, metres."""
        rotation = self.world_to_camera[:3, :3]
        return -rotation.T @ self.world_to_camera[:3, 3]

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Camera:
        return Camera(
            self.K.to(device=device, dtype=dtype),
            self.world_to_camera.to(device=device, dtype=dtype),
            self.width,
            self.height,
        )

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resized by `factor` (pixel centres stay at +0.5)."""
        K = self.K.clone()
        K[:2] *= factor
        return Camera(K, self.world_to_camera, round(self.width * factor), round(self.height * factor))


def look_at(eye: torch.Tensor, target: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """(4, 4) world->camera transform of an OpenCV camera at `eye` looking at `target`.

    eye, target, up: (3,) world frame, metres; `up` is the world direction that appears up in the image.
    """
    forward = torch.nn.functional.normalize(target - eye, dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(forward, up), dim=0)
    down = torch.linalg.cross(forward, right)
    rotation = torch.stack([right, down, forward])
    view = torch.eye(4, dtype=eye.dtype)
    view[:3, :3] = rotation
    view[:3, 3] = -rotation @ eye
    return view
