"""Conversions between rotation representations (batched, differentiable), below every package that poses bodies.

Conventions: rotations act on column vectors; quaternions are (w, x, y, z); angles are radians.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

# Below this squared angle (rad^2) Rodrigues' coefficients use their Taylor series.
_SMALL_ANGLE_SQ = 1e-6


def _skew(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) vectors -> (..., 3, 3) cross-product matrices [v]x."""
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(v.shape + (3,))


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula. axis_angle: (..., 3) axis times angle in radians -> (..., 3, 3) rotations.

    R = I + a K + b K^2 with K = [axis_angle]x, a = sin(t)/t, b = (1 - cos t)/t^2; a and b use their
    Taylor series near t = 0, so values and gradients are exact there.
    """
    angle_sq = (axis_angle * axis_angle).sum(-1)
    small = angle_sq < _SMALL_ANGLE_SQ
    angle = torch.sqrt(torch.where(small, torch.ones_like(angle_sq), angle_sq))
    a = torch.where(small, 1.0 - angle_sq / 6.0 + angle_sq * angle_sq / 120.0, torch.sin(angle) / angle)
    half_sinc = torch.sin(0.5 * angle) / angle  # (1 - cos t) / t^2 = 2 (sin(t/2) / t)^2, no cancellation
    b = torch.where(small, 0.5 - angle_sq / 24.0 + angle_sq * angle_sq / 720.0, 2.0 * half_sinc * half_sinc)
    k = _skew(axis_angle)
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def quaternion_to_matrix(quats: torch.Tensor) -> torch.Tensor:
    """(..., 4) quaternions w x y z, any non-zero norm -> (..., 3, 3) rotation matrices."""
    w, x, y, z = F.normalize(quats, dim=-1).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(quats.shape[:-1] + (3, 3))  # fmt: skip


def rotation_6d_to_matrix(columns: torch.Tensor) -> torch.Tensor:
    """(..., 3, 2) two 3-vectors as columns -> (..., 3, 3) rotations by Gram-Schmidt (Zhou et al. 2019):
    b1 = normalise(c0), b2 = normalise(c1 - (b1.c1) b1), b3 = b1 x b2, R = [b1 b2 b3] as columns."""
    first = F.normalize(columns[..., 0], dim=-1)
    second = columns[..., 1]
    second = F.normalize(second - (first * second).sum(-1, keepdim=True) * first, dim=-1)
    return torch.stack([first, second, torch.linalg.cross(first, second, dim=-1)], dim=-1)


def matrix_to_axis_angle(rotations: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotations -> (..., 3) axis-angle with angle in [0, pi]; differentiable.

    Goes through the unit quaternion, taken (Shepperd's method) from whichever of 1 + trace and 1 + 2 R_ii - trace
    is largest (at least 1), so it is well conditioned at every angle, pi included.
    """
    r = rotations
    r00, r01, r02 = r[..., 0, 0], r[..., 0, 1], r[..., 0, 2]
    r10, r11, r12 = r[..., 1, 0], r[..., 1, 1], r[..., 1, 2]
    r20, r21, r22 = r[..., 2, 0], r[..., 2, 1], r[..., 2, 2]
    # the four candidates (w, x, y, z) * 4 * (the large component), stacked as (..., 4 candidates, 4)
    traces = torch.stack([1 + r00 + r11 + r22, 1 + r00 - r11 - r22, 1 - r00 + r11 - r22, 1 - r00 - r11 + r22], -1)
    candidates = torch.stack(
        [
            torch.stack([traces[..., 0], r21 - r12, r02 - r20, r10 - r01], -1),
            torch.stack([r21 - r12, traces[..., 1], r10 + r01, r02 + r20], -1),
            torch.stack([r02 - r20, r10 + r01, traces[..., 2], r21 + r12], -1),
            torch.stack([r10 - r01, r02 + r20, r21 + r12, traces[..., 3]], -1),
        ],
        -2,
    ) / (2.0 * torch.sqrt(traces.clamp_min(0.25)))[..., None]  # the chosen trace is >= 1; others stay finite
    best = traces.argmax(-1)[..., None, None].expand(traces.shape[:-1] + (1, 4))
    quats = F.normalize(candidates.gather(-2, best)[..., 0, :], dim=-1)
    quats = torch.where(quats[..., :1] < 0, -quats, quats)
    w, vector = quats[..., 0], quats[..., 1:]
    sine_sq = (vector * vector).sum(-1)
    small = sine_sq < 1e-12
    sine = torch.sqrt(torch.where(small, torch.ones_like(sine_sq), sine_sq))
    # angle / sin(angle / 2), by its series 2 / w (1 - sin^2 / (3 w^2)) for small angles
    scale = torch.where(small, 2.0 / w * (1.0 - sine_sq / (3.0 * w * w)), 2.0 * torch.atan2(sine, w) / sine)
    return vector * scale[..., None]

