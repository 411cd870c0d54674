"""SMPL kinematics and skinning against independent float64 references."""

from __future__ import annotations

import pytest
import torch

from avatarperfect_cli.body.base import NUM_JOINTS, SMPL_PARENTS
from avatarperfect_cli.body.skeleton import (
    axis_angle_to_matrix,
    forward_kinematics,
    matrix_to_quaternion,
    quaternion_to_matrix,
    skin_gaussians,
    skin_points,
)


def _skew(v: torch.Tensor) -> torch.Tensor:
    m = torch.zeros(v.shape[:-1] + (3, 3), dtype=v.dtype)
    m[..., 0, 1], m[..., 0, 2], m[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    return m - m.transpose(-1, -2)


def _rest_joints(generator: torch.Generator) -> torch.Tensor:
    """A plausible skeleton: each joint a short random offset from its parent."""
    joints = torch.zeros(NUM_JOINTS, 3, dtype=torch.float64)
    joints[0] = torch.tensor([0.0, 0.9, 0.0], dtype=torch.float64)
    for joint, parent in enumerate(SMPL_PARENTS[1:], start=1):
        joints[joint] = joints[parent] + 0.15 * torch.randn(3, generator=generator, dtype=torch.float64)
    return joints


def _sparse_weights(n: int, generator: torch.Generator, per_point: int = 3) -> torch.Tensor:
    weights = torch.zeros(n, NUM_JOINTS, dtype=torch.float64)
    joints = torch.randint(0, NUM_JOINTS, (n, per_point), generator=generator)
    weights.scatter_add_(1, joints, torch.rand(n, per_point, generator=generator, dtype=torch.float64) + 0.1)
    return weights / weights.sum(1, keepdim=True)


def _bone_weights(n: int, generator: torch.Generator) -> torch.Tensor:
    """Like a body's skin: each point weighted between one joint and its parent."""
    joints = torch.randint(1, NUM_JOINTS, (n,), generator=generator)
    share = torch.rand(n, generator=generator, dtype=torch.float64)
    weights = torch.zeros(n, NUM_JOINTS, dtype=torch.float64)
    weights[torch.arange(n), joints] = share
    weights[torch.arange(n), torch.tensor(SMPL_PARENTS)[joints]] = 1.0 - share
    return weights


def _reference_kinematics(body_pose: torch.Tensor, rest_joints: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
    """Per-joint recursion on 4x4 matrices: G_j = G_parent [R_j | J_j - J_parent], A_j = G_j [I | J_j]^-1,
    with R_j = exp([pose_j]x) by the matrix exponential."""
    batch = body_pose.shape[0]
    result = torch.zeros(batch, NUM_JOINTS, 4, 4, dtype=torch.float64)
    for b in range(batch):
        world: list[torch.Tensor] = []
        for joint, parent in enumerate(SMPL_PARENTS):
            local = torch.eye(4, dtype=torch.float64)
            local[:3, :3] = torch.linalg.matrix_exp(_skew(body_pose[b, joint]))
            if parent < 0:
                local[:3, 3] = rest_joints[joint] + transl[b]
                world.append(local)
            else:
                local[:3, 3] = rest_joints[joint] - rest_joints[parent]
                world.append(world[parent] @ local)
            rest = torch.eye(4, dtype=torch.float64)
            rest[:3, 3] = rest_joints[joint]
            result[b, joint] = world[joint] @ torch.linalg.inv(rest)
    return result


def _subtree(joint: int) -> set[int]:
    members = {joint}
    for child, parent in enumerate(SMPL_PARENTS):
        if parent in members:
            members.add(child)
    return members


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


def test_forward_kinematics_matches_recursive_reference() -> None:
    generator = torch.Generator().manual_seed(2)
    joints = _rest_joints(generator)
    pose = 0.6 * torch.randn(3, NUM_JOINTS, 3, generator=generator, dtype=torch.float64)
    transl = torch.randn(3, 3, generator=generator, dtype=torch.float64)
    torch.testing.assert_close(forward_kinematics(pose, joints, transl), _reference_kinematics(pose, joints, transl))


def test_identity_pose_leaves_points_and_gaussians_unchanged() -> None:
    generator = torch.Generator().manual_seed(3)
    joints = _rest_joints(generator).float()
    transforms = forward_kinematics(torch.zeros(1, NUM_JOINTS, 3), joints, torch.zeros(1, 3))
    assert torch.equal(transforms, torch.eye(4).expand(1, NUM_JOINTS, 4, 4))
    points = torch.randn(50, 3, generator=generator)
    quats = torch.randn(50, 4, generator=generator)
    weights = _sparse_weights(50, generator).float()
    torch.testing.assert_close(skin_points(points, weights, transforms)[0], points)
    means, posed_quats = skin_gaussians(points, quats, weights, transforms[0])
    torch.testing.assert_close(means, points)
    torch.testing.assert_close(posed_quats, quats)


@pytest.mark.parametrize("joint", [4, 9, 18])
def test_rotating_a_joint_moves_only_its_subtree(joint: int) -> None:
    generator = torch.Generator().manual_seed(4)
    joints = _rest_joints(generator)
    weights = _bone_weights(400, generator)
    points = weights @ joints + 0.05 * torch.randn(400, 3, generator=generator, dtype=torch.float64)
    quats = torch.randn(400, 4, generator=generator, dtype=torch.float64)
    pose = torch.zeros(1, NUM_JOINTS, 3, dtype=torch.float64)
    pose[0, joint] = torch.tensor([0.7, -0.4, 0.3], dtype=torch.float64)
    posed_transforms = forward_kinematics(pose, joints, torch.zeros(1, 3, dtype=torch.float64))
    rest_transforms = forward_kinematics(torch.zeros_like(pose), joints, torch.zeros(1, 3, dtype=torch.float64))

    in_subtree = torch.zeros(NUM_JOINTS, dtype=torch.bool)
    in_subtree[list(_subtree(joint))] = True
    outside = (weights[:, in_subtree] == 0).all(1)
    inside = (weights[:, ~in_subtree] == 0).all(1)
    assert outside.sum() > 50 and inside.sum() > 5

    posed = skin_points(points, weights, posed_transforms)[0]
    rest = skin_points(points, weights, rest_transforms)[0]
    assert torch.equal(posed[outside], rest[outside])
    moved = (posed[inside] - points[inside]).norm(dim=-1)
    # points rigidly attached to the rotated subtree keep their distance to the joint
    distance_before = (points[inside] - joints[joint]).norm(dim=-1)
    distance_after = (posed[inside] - joints[joint]).norm(dim=-1)
    torch.testing.assert_close(distance_after, distance_before)
    assert (moved > 1e-3).float().mean() > 0.9

    means, posed_quats = skin_gaussians(points, quats, weights, posed_transforms[0])
    rest_means, rest_quats = skin_gaussians(points, quats, weights, rest_transforms[0])
    assert torch.equal(means[outside], rest_means[outside])
    assert torch.equal(posed_quats[outside], rest_quats[outside])


def test_skin_gaussians_matches_svd_polar_reference() -> None:
    generator = torch.Generator().manual_seed(5)
    joints = _rest_joints(generator)
    pose = 0.5 * torch.randn(1, NUM_JOINTS, 3, generator=generator, dtype=torch.float64)
    transforms = forward_kinematics(pose, joints, torch.randn(1, 3, generator=generator, dtype=torch.float64))[0]
    means = torch.randn(300, 3, generator=generator, dtype=torch.float64)
    quats = torch.randn(300, 4, generator=generator, dtype=torch.float64)
    weights = _sparse_weights(300, generator)

    posed_means, posed_quats = skin_gaussians(means, quats, weights, transforms)

    blended = torch.einsum("nj,jab->nab", weights, transforms)
    torch.testing.assert_close(posed_means, (blended[:, :3, :3] @ means[..., None])[..., 0] + blended[:, :3, 3])
    u, _, vh = torch.linalg.svd(blended[:, :3, :3])
    polar = u @ vh
    assert (torch.linalg.det(polar) > 0).all()
    torch.testing.assert_close(quaternion_to_matrix(posed_quats), polar @ quaternion_to_matrix(quats))
    torch.testing.assert_close(posed_quats.norm(dim=-1), quats.norm(dim=-1))
    torch.testing.assert_close(skin_points(means, weights, transforms[None])[0], posed_means)


@pytest.mark.parametrize("scale", [0.0, 0.8])
def test_skinning_gradcheck_wrt_pose_translation_and_gaussians(scale: float) -> None:
    generator = torch.Generator().manual_seed(6)
    joints = _rest_joints(generator)
    pose = (scale * torch.randn(2, NUM_JOINTS, 3, generator=generator, dtype=torch.float64)).requires_grad_()
    transl = torch.randn(2, 3, generator=generator, dtype=torch.float64).requires_grad_()
    points = torch.randn(5, 3, generator=generator, dtype=torch.float64).requires_grad_()
    quats = torch.randn(5, 4, generator=generator, dtype=torch.float64).requires_grad_()
    weights = _sparse_weights(5, generator, per_point=4)

    def posed_points(pose: torch.Tensor, transl: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        return skin_points(points, weights, forward_kinematics(pose, joints, transl))

    def posed_gaussians(
        pose: torch.Tensor, transl: torch.Tensor, means: torch.Tensor, quats: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        return skin_gaussians(means, quats, weights, forward_kinematics(pose, joints, transl)[0])

    assert torch.autograd.gradcheck(posed_points, (pose, transl, points))
    first_pose, first_transl = pose[:1].detach().requires_grad_(), transl[:1].detach().requires_grad_()
    assert torch.autograd.gradcheck(posed_gaussians, (first_pose, first_transl, points, quats))


def test_quaternion_round_trip_in_every_branch() -> None:
    generator = torch.Generator().manual_seed(7)
    quats = torch.nn.functional.normalize(torch.randn(200, 4, generator=generator, dtype=torch.float64), dim=-1)
    # near-pi rotations about each axis select the x, y and z branches; the identity the w branch
    special = torch.tensor(
        [[1, 0, 0, 0], [1e-3, 1, 0, 0], [1e-3, 0, 1, 0], [1e-3, 0, 0, 1], [0, 1, 1, 0], [0, 0, -1, 1]],
        dtype=torch.float64,
    )
    quats = torch.cat([quats, torch.nn.functional.normalize(special, dim=-1)])
    recovered = matrix_to_quaternion(quaternion_to_matrix(quats))
    signs = torch.where(quats[:, :1] < 0, -1.0, 1.0).to(torch.float64)
    torch.testing.assert_close(recovered, quats * signs)
    rotations = torch.linalg.matrix_exp(_skew(2.5 * torch.randn(100, 3, generator=generator, dtype=torch.float64)))
    torch.testing.assert_close(quaternion_to_matrix(matrix_to_quaternion(rotations)), rotations)
