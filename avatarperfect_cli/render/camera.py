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


def rotation_about(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """(3, 3) rotation by `angle` (radians, a 0-d tensor, differentiable) about the unit `axis` (3,) (Rodrigues),
    on the axis's device."""
    cross = torch.zeros(3, 3, dtype=axis.dtype, device=axis.device)
    cross[0, 1], cross[0, 2], cross[1, 2] = -axis[2], axis[1], -axis[0]
    cross = cross - cross.T
    identity = torch.eye(3, dtype=axis.dtype, device=axis.device)
    return identity + torch.sin(angle) * cross + (1 - torch.cos(angle)) * (cross @ cross)


# Framing keeps every part of the subject within this magnification of its centre (`framing_distance`).
MAX_MAGNIFICATION = 1.5


def framing_distance(
    points: torch.Tensor, rotation: torch.Tensor, K: torch.Tensor, width: int, height: int, fill: float,
    max_magnification: float = MAX_MAGNIFICATION,
) -> torch.Tensor:
    """Distance, metres, from the look-at point to a camera with `rotation` (3, 3, world -> camera) and
    intrinsics K, W x H, at which every point fits inside `fill` of the image around the principal point
    and no point is nearer than 1 / max_magnification of that distance (so no part looks more than
    `max_magnification` times larger than at the look-at point: a foot raised toward the camera would
    otherwise fill the picture with its blurred close-up).

    points: (N, 3) relative to the look-at point, world frame. The camera sits at -distance * forward.
    Returns a 0-d tensor, differentiable w.r.t. the points (through the extreme ones).
    """
    if max_magnification <= 1.0:
        raise ValueError(f"max_magnification must exceed 1, got {max_magnification}")
    x, y, z = (points @ rotation.detach().to(points.dtype).T).unbind(-1)
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    # the extreme points decide: the largest offset / (room on that side) minus depth, per side and axis;
    # a point at depth z (relative) sits at distance + z, which must be >= distance / max_magnification
    need = torch.stack([
        fx * x / (fill * (width - cx)) - z, -fx * x / (fill * cx) - z,
        fy * y / (fill * (height - cy)) - z, -fy * y / (fill * cy) - z, 0.05 - z,  # 5 cm in front at least
        -z / (1.0 - 1.0 / max_magnification),
    ])  # fmt: skip
    return need.max()
