"""Retargeting a pose to another skeleton: exact where an exact answer exists, optimal where it does not."""

from __future__ import annotations

import torch

from avatarperfect_cli.body import SMPL_JOINT_NAMES, SMPL_PARENTS, forward_kinematics, load_body_template, posed_joints
from avatarperfect_cli.body.base import joint_displacements
from avatarperfect_cli.body.retarget import RetargetConfig, retarget_pose


def _pose(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    body_pose = 0.35 * torch.randn(24, 3, generator=generator, dtype=torch.float64)
    return body_pose, torch.tensor([0.1, -0.2, 2.5], dtype=torch.float64)


def _joints(body_pose: torch.Tensor, rest_joints: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
    return posed_joints(forward_kinematics(body_pose[None], rest_joints, transl[None])[0], rest_joints)


def _rest_joints() -> torch.Tensor:
    return load_body_template("anny").rest_joints.double()


def test_the_same_skeleton_gets_the_same_pose_back() -> None:
    rest_joints = _rest_joints()
    body_pose, transl = _pose(0)
    pose, position = retarget_pose(body_pose, transl, rest_joints, rest_joints)
    torch.testing.assert_close(pose, body_pose, rtol=0, atol=1e-12)
    torch.testing.assert_close(position, transl, rtol=0, atol=1e-12)


def test_a_shifted_skeleton_keeps_the_angles_and_moves_the_translation() -> None:
    rest_joints = _rest_joints()
    shift = torch.tensor([0.03, -0.05, 0.02], dtype=torch.float64)
    body_pose, transl = _pose(1)
    pose, position = retarget_pose(body_pose, transl, rest_joints, rest_joints + shift)
    torch.testing.assert_close(pose, body_pose, rtol=0, atol=1e-5)  # radians: 10 µm at a metre
    torch.testing.assert_close(position, transl - shift, rtol=0, atol=1e-6)


def test_longer_legs_are_bent_to_put_the_joints_where_the_shorter_ones_are() -> None:
    rest_joints = _rest_joints()
    bone_offsets = torch.zeros(24, 3, dtype=torch.float64)
    for name in ("left_knee", "right_knee", "left_ankle", "right_ankle", "left_elbow", "right_elbow"):
        joint = SMPL_JOINT_NAMES.index(name)
        bone = rest_joints[joint] - rest_joints[SMPL_PARENTS[joint]]
        bone_offsets[joint] = 0.08 * bone  # 8% longer thighs, shins and upper arms
    target = rest_joints + joint_displacements(bone_offsets)
    body_pose, transl = _pose(2)
    goal = _joints(body_pose, rest_joints, transl)
    pose, position = retarget_pose(body_pose, transl, rest_joints, target)
    before = (_joints(body_pose, target, transl) - goal).norm(dim=-1).mean()
    after = (_joints(pose, target, position) - goal).norm(dim=-1).mean()
    assert after < 0.8 * before  # longer bones cannot reach every joint: their ends are bent back in

    # The same objective minimised by plain gradient descent from another start ends no lower.
    config = RetargetConfig()

    def objective(angles: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
        value = ((_joints(angles, target, offset) - goal) / config.joint_scale).square().sum(dim=-1).mean()
        return value + config.prior * ((angles - body_pose) / 0.1).square().sum(dim=-1).mean()

    angles = torch.zeros_like(body_pose, requires_grad=True)
    offset = transl.clone().requires_grad_(True)
    optimizer = torch.optim.Adam([angles, offset], lr=0.01)
    for _ in range(2000):
        optimizer.zero_grad()
        objective(angles, offset).backward()
        optimizer.step()
    reached = objective(pose, position).item()
    assert reached <= objective(angles.detach(), offset.detach()).item() + 1e-3
