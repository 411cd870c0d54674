"""EWA projection of 3D Gaussians through a pinhole camera (torch, differentiable by autograd)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from avatarperfect_cli.render.camera import Camera

ALPHA_MIN = 1.0 / 255.0


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """(..., 4) quaternions w x y z (any norm) -> (..., 3, 3) rotation matrices."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(quats.shape[:-1] + (3, 3))  # fmt: skip


@dataclass
class Projection:
    """Screen-space Gaussians.

    means2d: (N, 2) pixels; conics: (N, 3) inverse 2D covariance (a, b, c) in 1/pixel^2;
    depths: (N,) camera z, metres; extents: (N, 2) half-size of the box holding every pixel with
    alpha >= 1/255, pixels (no grad); drawn: (N,) bool, in front of the camera and on screen.
    """

    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    extents: torch.Tensor
    drawn: torch.Tensor

    @property
    def radii(self) -> torch.Tensor:
        """(N,) int32 radius in pixels of the drawn footprint, 0 where not drawn."""
        radius = torch.ceil(self.extents.max(dim=-1).values)
        return torch.where(self.drawn, radius, torch.zeros_like(radius)).to(torch.int32)


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    camera: Camera,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
) -> Projection:
    """Project Gaussians (gsplat's classic EWA: clamped Jacobian, eps2d added to the 2D covariance).

    means (N, 3) metres, world frame; quats (N, 4) w x y z; scales (N, 3) standard deviations,
    metres; opacities (N,) in [0, 1].
    """
    rotation = camera.world_to_camera[:3, :3]
    means_cam = means @ rotation.T + camera.world_to_camera[:3, 3]
    x, y, z = means_cam.unbind(-1)
    in_depth = (z > near_plane) & (z < far_plane)
    z = torch.where(in_depth, z, torch.ones_like(z))  # keeps gradients finite for culled Gaussians

    fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
    margin_x = 0.3 * 0.5 * camera.width / fx
    margin_y = 0.3 * 0.5 * camera.height / fy
    tx = z * torch.clamp(x / z, -(cx / fx + margin_x), (camera.width - cx) / fx + margin_x)
    ty = z * torch.clamp(y / z, -(cy / fy + margin_y), (camera.height - cy) / fy + margin_y)
    zero = torch.zeros_like(z)
    jacobian = torch.stack(
        [fx / z, zero, -fx * tx / (z * z), zero, fy / z, -fy * ty / (z * z)], dim=-1
    ).reshape(-1, 2, 3)
    # cov2d = (J R M)(J R M)^T with M = rotation(q) diag(s): one (2x3)(3x3) product per Gaussian.
    screen_axes = (jacobian @ rotation) @ (quat_to_rotmat(quats) * scales[:, None, :])
    cov2d = screen_axes @ screen_axes.transpose(1, 2)
    cov_a = cov2d[:, 0, 0] + eps2d
    cov_b = cov2d[:, 0, 1]
    cov_c = cov2d[:, 1, 1] + eps2d
    det = cov_a * cov_c - cov_b * cov_b
    valid = in_depth & (det > 0) & (opacities >= ALPHA_MIN)
    det = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([cov_c / det, -cov_b / det, cov_a / det], dim=-1)
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], dim=-1)

    with torch.no_grad():
        level = 2.0 * torch.log(torch.clamp_min(opacities, ALPHA_MIN) / ALPHA_MIN)
        extents = torch.sqrt(level[:, None] * torch.stack([cov_a, cov_c], dim=-1).clamp_min(0))
        extents = extents * math.sqrt(1.01) + 0.1  # the kernels' margin, so binning never misses a pixel
        on_screen = (
            (means2d[:, 0] + extents[:, 0] > 0)
            & (means2d[:, 0] - extents[:, 0] < camera.width)
            & (means2d[:, 1] + extents[:, 1] > 0)
            & (means2d[:, 1] - extents[:, 1] < camera.height)
        )
        drawn = valid & on_screen
    return Projection(means2d, conics, means_cam[:, 2], extents, drawn)
