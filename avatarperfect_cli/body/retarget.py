"""Retargeting: the pose of one skeleton that puts its joints where another skeleton's posed joints are.

Two bodies of different proportions in the same joint angles stand differently: a longer thigh puts the
knee lower and the foot further out. Retargeting solves for the angles (and the translation) of the
target skeleton whose posed joints lie closest to the source's, with a weak pull toward the source's
angles for what joint positions do not decide (a limb's twist about its own axis).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from avatarperfect_cli.body.skeleton import forward_kinematics, posed_joints


@dataclass
class RetargetConfig:
    """joint_scale: joint distance that costs 1, metres; prior: cost of a joint angle 0.1 rad from the source's
    (the pull that fixes twists); iterations: L-BFGS iterations."""

    joint_scale: float = 0.01
    prior: float = 0.01
    iterations: int = 100


def retarget_pose(
    body_pose: torch.Tensor,
    transl: torch.Tensor,
    rest_joints: torch.Tensor,
    target_rest_joints: torch.Tensor,
    config: RetargetConfig | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(body_pose (24, 3), transl (3,)) float64 of the skeleton `target_rest_joints` (24, 3) whose posed joints
    lie closest (least squares) to those of `rest_joints` (24, 3) posed by body_pose (24, 3) axis-angle and
    transl (3,) metres. The solve starts from the source's angles and translation, so a target whose skeleton is
    the source's gets the source's pose back."""
    config = config or RetargetConfig()
    body_pose, transl = body_pose.detach().double(), transl.detach().double()
    target_rest_joints = target_rest_joints.detach().double()
    source_rest_joints = rest_joints.detach().double()
    goal = posed_joints(forward_kinematics(body_pose[None], source_rest_joints, transl[None])[0], source_rest_joints)
    pose = body_pose.clone().requires_grad_(True)
    position = transl.clone().requires_grad_(True)
    optimizer = torch.optim.LBFGS(
        [pose, position], max_iter=config.iterations, tolerance_grad=1e-12, tolerance_change=1e-15, line_search_fn="strong_wolfe"
    )

    def loss() -> torch.Tensor:
        optimizer.zero_grad()
        joints = posed_joints(forward_kinematics(pose[None], target_rest_joints, position[None])[0], target_rest_joints)
        value = ((joints - goal) / config.joint_scale).square().sum(dim=-1).mean()
        value = value + config.prior * ((pose - body_pose) / 0.1).square().sum(dim=-1).mean()
        value.backward()
        return value

    optimizer.step(loss)
    return pose.detach(), position.detach()
