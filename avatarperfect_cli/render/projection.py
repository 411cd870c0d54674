"""EWA projection of 3D Gaussians through a pinhole camera, differentiable (numba forward/backward)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from avatarperfect_cli.render import projection_kernels as kernels
from avatarperfect_cli.render.camera import Camera


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
        radius = torch.ceil(self.extents.max(dim=-1).values) if len(self.extents) else self.extents[:, 0]
        return torch.where(self.drawn, radius, torch.zeros_like(radius)).to(torch.int32)


def _array(tensor: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(tensor.detach().cpu().numpy())


def _camera_arrays(camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """View matrix, (fx, fy, cx, cy) and the clamp limits of x/z and y/z (gsplat: 15% margin)."""
    K = camera.K.detach().double().cpu()
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    margin_x, margin_y = 0.15 * camera.width / fx, 0.15 * camera.height / fy
    limits = [cx / fx + margin_x, (camera.width - cx) / fx + margin_x, cy / fy + margin_y, (camera.height - cy) / fy + margin_y]
    return _array(camera.world_to_camera), np.array([fx, fy, cx, cy], dtype=np.float64), np.array(limits, dtype=np.float64)


class _ProjectGaussians(torch.autograd.Function):
    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        means: torch.Tensor,
        quats: torch.Tensor,
        scales: torch.Tensor,
        opacities: torch.Tensor,
        camera: Camera,
        near_plane: float,
        far_plane: float,
        eps2d: float,
    ) -> tuple[torch.Tensor, ...]:
        view, intrinsics, limits = _camera_arrays(camera)
        view = view.astype(_array(means).dtype)
        inputs = (_array(means), _array(quats), _array(scales))
        means2d, conics, depths, extents, drawn = kernels.project_forward(
            *inputs, _array(opacities), view, intrinsics, limits, camera.width, camera.height, near_plane, far_plane, eps2d
        )
        ctx.saved = (*inputs, view, intrinsics, limits, conics, drawn)
        extents_t, drawn_t = torch.from_numpy(extents), torch.from_numpy(drawn)
        ctx.mark_non_differentiable(extents_t, drawn_t)
        return torch.from_numpy(means2d), torch.from_numpy(conics), torch.from_numpy(depths), extents_t, drawn_t

    @staticmethod
    def backward(  # type: ignore[override]
        ctx: Any, grad_means2d: torch.Tensor, grad_conics: torch.Tensor, grad_depths: torch.Tensor, *_: Any
    ) -> tuple[torch.Tensor | None, ...]:
        grads = kernels.project_backward(*ctx.saved, _array(grad_means2d), _array(grad_conics), _array(grad_depths))
        return (*(torch.from_numpy(g) for g in grads), None, None, None, None, None)


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

    means (N, 3) metres, world frame; quats (N, 4) w x y z, any norm; scales (N, 3) standard
    deviations, metres; opacities (N,) in [0, 1] (Gaussians below 1/255 are never drawn).
    Differentiable w.r.t. means, quats and scales.
    """
    outputs = _ProjectGaussians.apply(means, quats, scales, opacities, camera, near_plane, far_plane, eps2d)
    return Projection(*outputs)
