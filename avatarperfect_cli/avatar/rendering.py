"""Render a skinned avatar in a body pose."""

from __future__ import annotations

import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.render import Camera, RenderOutput, rasterization


def render_avatar(
    avatar: Avatar,
    body_pose: torch.Tensor,
    transl: torch.Tensor,
    camera: Camera,
    background: torch.Tensor,
    region: tuple[slice, slice] | None = None,
    transforms: torch.Tensor | None = None,
) -> RenderOutput:
    """Pose the avatar (body_pose (24, 3) axis-angle, transl (3,) metres) and render it with its
    active SH degree over `background` (3,); `region` as in `rasterization`. Differentiable w.r.t. the
    avatar and the pose.
    transforms: the pose's `avatar.joint_transforms(body_pose, transl)`, when the caller kept them."""
    if transforms is None:
        transforms = avatar.joint_transforms(body_pose, transl)
    means, quats = avatar.skin(transforms)
    return rasterization(
        means, quats, avatar.scales, avatar.opacities, avatar.sh, camera,
        sh_degree=avatar.active_sh_degree, background=background, region=region,
    )  # fmt: skip
