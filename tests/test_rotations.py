"""Rotation conversions against independent references: the matrix exponential, half-angle quaternions,
Gram-Schmidt's defining properties."""

from __future__ import annotations

import math

import torch

from avatarperfect_cli.rotations import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    quaternion_to_matrix,
    rotation_6d_to_matrix,
)


def _skew(v: torch.Tensor) -> torch.Tensor:
    m = torch.zeros(v.shape[:-1] + (3, 3), dtype=v.dtype)
    m[..., 0, 1], m[..., 0, 2], m[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    return m - m.transpose(-1, -2)


def test_axis_angle_matches_matrix_exponential_including_tiny_angles() -> None:
    generator = torch.Generator().manual_seed(0)
    directions = torch.nn.functional.normalize(torch.randn(6, 3, generator=generator, dtype=torch.float64), dim=-1)
    angles = torch.tensor([0.0, 1e-9, 1e-4, 1e-3, 0.5, 3.0], dtype=torch.float64)
    axis_angle = directions * angles[:, None]
    torch.testing.assert_close(axis_angle_to_matrix(axis_angle), torch.linalg.matrix_exp(_skew(axis_angle)))
    # float32 keeps full precision at small angles (no 1 - cos cancellation)
    small = (directions * 2e-3).float()
    torch.testing.assert_close(
        axis_angle_to_matrix(small).double(), torch.linalg.matrix_exp(_skew(small.double())), atol=1e-7, rtol=0
    )


def test_axis_angle_gradcheck_at_zero_and_random() -> None:
    zero = torch.zeros(2, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(axis_angle_to_matrix, (zero,))
    random = torch.randn(4, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1)).requires_grad_()
    assert torch.autograd.gradcheck(axis_angle_to_matrix, (random,))


def test_quaternion_to_matrix_is_the_half_angle_rotation_at_any_norm() -> None:
    """q = s (cos(t/2), sin(t/2) axis) rotates by t about axis for every scale s != 0, sign included."""
    generator = torch.Generator().manual_seed(2)
    axis_angle = 3.0 * torch.randn(50, 3, generator=generator, dtype=torch.float64)
    angle = axis_angle.norm(dim=-1, keepdim=True)
    quats = torch.cat([torch.cos(angle / 2), torch.sin(angle / 2) * axis_angle / angle], dim=-1)
    scales = torch.linspace(-3.0, 3.0, 50, dtype=torch.float64)[:, None]
    scales = torch.where(scales.abs() < 0.1, torch.full_like(scales, 0.5), scales)
    expected = torch.linalg.matrix_exp(_skew(axis_angle))
    torch.testing.assert_close(quaternion_to_matrix(quats * scales), expected)


def test_rotation_6d_to_matrix_gives_proper_rotations() -> None:
    columns = torch.randn(500, 3, 2, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    rotations = rotation_6d_to_matrix(columns)
    eye = torch.eye(3, dtype=torch.float64).expand(500, 3, 3)
    assert torch.allclose(rotations.transpose(1, 2) @ rotations, eye, atol=1e-12)
    assert torch.allclose(torch.linalg.det(rotations), torch.ones(500, dtype=torch.float64), atol=1e-12)
    # Gram-Schmidt: the first column is the first input's direction, the second lies in the inputs' plane
    first = columns[..., 0] / columns[..., 0].norm(dim=-1, keepdim=True)
    assert torch.allclose(rotations[..., 0], first, atol=1e-12)
    normal = torch.linalg.cross(columns[..., 0], columns[..., 1], dim=-1)
    assert torch.allclose((rotations[..., 1] * normal).sum(-1), torch.zeros(500, dtype=torch.float64), atol=1e-10)
    assert ((rotations[..., 1] * columns[..., 1]).sum(-1) > 0).all()


def test_matrix_to_axis_angle_round_trips_at_every_angle() -> None:
    generator = torch.Generator().manual_seed(4)
    axes = torch.nn.functional.normalize(torch.randn(9, 3, generator=generator, dtype=torch.float64), dim=-1)
    angles = [0.0, 1e-9, 1e-4, 0.5, 2.0, 3.0, math.pi - 1e-4, math.pi - 1e-8, math.pi]
    angles = torch.tensor(angles, dtype=torch.float64)
    axis_angle = torch.cat([axes * angles[:, None], -axes[:4] * angles[-4:, None]])
    recovered = matrix_to_axis_angle(axis_angle_to_matrix(axis_angle))
    assert torch.allclose(axis_angle_to_matrix(recovered), axis_angle_to_matrix(axis_angle), atol=1e-12)
    assert torch.allclose(recovered.norm(dim=-1), axis_angle.norm(dim=-1), atol=1e-7)
    below_pi = axis_angle.norm(dim=-1) < 3.1
    assert torch.allclose(recovered[below_pi], axis_angle[below_pi], atol=1e-12)
    # gradient of the round trip is the identity away from pi
    point = (axes[4] * 2.0).requires_grad_()
    assert torch.autograd.gradcheck(lambda v: matrix_to_axis_angle(axis_angle_to_matrix(v)), (point,))
    jacobian = torch.autograd.functional.jacobian(lambda v: matrix_to_axis_angle(axis_angle_to_matrix(v)), point)
    assert torch.allclose(jacobian, torch.eye(3, dtype=torch.float64), atol=1e-10)
