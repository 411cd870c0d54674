"""Dense pure-PyTorch Gaussian renderer: the independent reference for the kernels' tests and benchmark.

It evaluates every Gaussian at every pixel with plain matrix algebra and lets autograd differentiate
it. It shares only conventions with the fast path (gsplat's: pixel centres at +0.5, clamped Jacobian,
eps2d, alpha clamp and thresholds, termination before T <= 1e-4), not code. Cost is O(pixels x N).
"""

from __future__ import annotations

import torch

from avatarperfect_cli.gaussians.sh import eval_sh
from avatarperfect_cli.render.camera import Camera


def _rotate(quats: torch.Tensor, vectors: torch.Tensor) -> torch.Tensor:
    """Rotate (3,) vectors by unit quaternions (N, 4) w x y z with the sandwich product q v q*."""
    w, xyz = quats[:, :1], quats[:, 1:]
    v = vectors.expand_as(xyz)
    t = 2.0 * torch.linalg.cross(xyz, v, dim=-1)
    return v + w * t + torch.linalg.cross(xyz, t, dim=-1)


def project_dense(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    camera: Camera,
    near_plane: float,
    far_plane: float,
    eps2d: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Returns means2d (N, 2), inverse 2D covariance (N, 2, 2), depths (N,), valid (N,) bool."""
    unit = quats / quats.norm(dim=-1, keepdim=True)
    eye = torch.eye(3, dtype=means.dtype)
    axes = torch.stack([_rotate(unit, eye[k]) for k in range(3)], dim=-1)  # columns = local axes
    cov3d = axes @ torch.diag_embed(scales**2) @ axes.transpose(1, 2)
    view_rotation = camera.world_to_camera[:3, :3]
    points = means @ view_rotation.T + camera.world_to_camera[:3, 3]
    depths = points[:, 2]
    valid = (depths > near_plane) & (depths < far_plane)
    z = torch.where(valid, depths, torch.ones_like(depths))
    fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
    limit_x = (cx / fx + 0.15 * camera.width / fx, (camera.width - cx) / fx + 0.15 * camera.width / fx)
    limit_y = (cy / fy + 0.15 * camera.height / fy, (camera.height - cy) / fy + 0.15 * camera.height / fy)
    u = torch.clamp(points[:, 0] / z, -limit_x[0], limit_x[1])
    v = torch.clamp(points[:, 1] / z, -limit_y[0], limit_y[1])
    jacobian = torch.zeros(means.shape[0], 2, 3, dtype=means.dtype)
    jacobian[:, 0, 0] = fx / z
    jacobian[:, 0, 2] = -fx * u / z
    jacobian[:, 1, 1] = fy / z
    jacobian[:, 1, 2] = -fy * v / z
    cov2d = jacobian @ view_rotation @ cov3d @ view_rotation.T @ jacobian.transpose(1, 2)
    cov2d = cov2d + eps2d * torch.eye(2, dtype=means.dtype)
    valid = valid & (torch.linalg.det(cov2d) > 0)
    cov2d = torch.where(valid[:, None, None], cov2d, torch.eye(2, dtype=means.dtype))
    means2d = torch.stack([fx * points[:, 0] / z + cx, fy * points[:, 1] / z + cy], dim=-1)
    return means2d, torch.linalg.inv(cov2d), depths, valid


def composite_dense(
    pixels: torch.Tensor,
    means2d: torch.Tensor,
    precision: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    background: torch.Tensor,
    order: torch.Tensor,
    valid: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Composite every Gaussian at pixel centres (P, 2), nearest first in `order`.

    Returns colour (P, C), alpha (P,) and per-Gaussian weights T * alpha (P, N) in `order`.
    """
    m, q, o, f = means2d[order], precision[order], opacities[order], features[order]
    delta = m[None, :, :] - pixels[:, None, :]
    sigma = 0.5 * torch.einsum("pni,nij,pnj->pn", delta, q, delta)
    alpha = torch.clamp(o[None, :] * torch.exp(-sigma), max=0.999)
    alpha = torch.where((alpha >= 1.0 / 255.0) & (sigma >= 0) & valid[order][None, :], alpha, 0.0)
    before = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha[:, :-1]], dim=1), dim=1)
    alpha = torch.where(before * (1.0 - alpha) > 1e-4, alpha, 0.0)
    transmittance = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha], dim=1), dim=1)
    weights = alpha * transmittance[:, :-1]
    final = transmittance[:, -1]
    return weights @ f + final[:, None] * background, 1.0 - final, weights


def rasterization_reference(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    camera: Camera,
    *,
    sh_degree: int | None = None,
    background: torch.Tensor | None = None,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Dense counterpart of `rasterization` (same arguments) for small scenes.

    Returns image (H, W, C), alpha (H, W), expected depth (H, W) and visibility (N,).
    """
    camera = camera.to(dtype=means.dtype)
    means2d, precision, depths, valid = project_dense(means, quats, scales, camera, near_plane, far_plane, eps2d)
    if sh_degree is not None:
        center = -camera.world_to_camera[:3, :3].T @ camera.world_to_camera[:3, 3]
        colors = eval_sh(colors, means - center, sh_degree)
    channels = colors.shape[1]
    if background is None:
        background = torch.zeros(channels, dtype=means.dtype)
    features = torch.cat([colors, depths[:, None]], dim=1)
    background = torch.cat([background.to(means.dtype), background.new_zeros(1).to(means.dtype)])
    ys, xs = torch.meshgrid(
        torch.arange(camera.height, dtype=means.dtype), torch.arange(camera.width, dtype=means.dtype), indexing="ij"
    )
    pixels = torch.stack([xs, ys], dim=-1).reshape(-1, 2) + 0.5
    order = torch.sort(depths.detach(), stable=True).indices
    color, alpha, weights = composite_dense(pixels, means2d, precision, opacities, features, background, order, valid)
    visibility = torch.zeros_like(opacities).index_add(0, order, weights.sum(0)).detach()
    image = color.reshape(camera.height, camera.width, channels + 1)
    alpha = alpha.reshape(camera.height, camera.width)
    depth = torch.where(alpha > 0, image[..., channels] / alpha.clamp_min(1e-10), torch.zeros_like(alpha))
    return image[..., :channels], alpha, depth, visibility
