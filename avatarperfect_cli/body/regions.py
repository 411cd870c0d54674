"""Body regions a person can name: which part of the body a canonical point belongs to.

A point's region comes from its skinning weights over SMPL's 24 joints (the limb, head or torso that
carries it) and, for the three places a video of a person standing or turning barely shows (the armpits,
the inner arms, the crotch), from where it lies relative to the rest skeleton. The rules need no mesh and
no normals, so they label a template's vertices and an avatar's Gaussians alike (canonical T-pose, SMPL's
frame: +Y up, +Z the front, +X the body's left, metres).
"""

from __future__ import annotations

import torch

from avatarperfect_cli.body.base import NUM_JOINTS

BODY_REGIONS: tuple[str, ...] = (
    "head", "torso", "upper arms", "forearms", "hands", "thighs", "lower legs", "feet", "armpits", "inner arms",
    "crotch",
)  # fmt: skip
REGION_INDEX = {name: index for index, name in enumerate(BODY_REGIONS)}
# The joints that carry each limb-level region (SMPL indices); the others belong to the torso.
_JOINT_REGION = {
    "head": (12, 15), "upper arms": (16, 17), "forearms": (18, 19), "hands": (20, 21, 22, 23), "thighs": (1, 2),
    "lower legs": (4, 5), "feet": (7, 8, 10, 11),
}  # fmt: skip
ARMPIT_RADIUS = 0.07  # metres around a point 7 cm below and 2 cm inside each shoulder joint
INNER_ARM_COSINE = 0.85  # the arm's underside in the T-pose: within ~32 degrees of straight down
CROTCH_THIGH_SHARE = 0.3  # the top 30% of the thigh, facing the other thigh
CROTCH_HALF_WIDTH = 0.06  # metres either side of the body's middle, below the hips
CROTCH_DEPTH = 0.04  # metres above the lowest point between the legs


def _joint_regions() -> torch.Tensor:
    """(24,) int64 region index of the body part each SMPL joint carries."""
    regions = torch.full((NUM_JOINTS,), REGION_INDEX["torso"], dtype=torch.int64)
    for name, joints in _JOINT_REGION.items():
        regions[list(joints)] = REGION_INDEX[name]
    return regions


def _radial(points: torch.Tensor, start: torch.Tensor, end: torch.Tensor) -> torch.Tensor:
    """(N, 3) unit directions from the line through `start` and `end` (3,) to `points` (N, 3), orthogonal to it."""
    axis = (end - start) / (end - start).norm()
    offset = points - start
    offset = offset - (offset @ axis)[:, None] * axis
    return offset / offset.norm(dim=1, keepdim=True).clamp_min(1e-12)


def body_regions(points: torch.Tensor, weights: torch.Tensor, rest_joints: torch.Tensor) -> torch.Tensor:
    """(N,) int64 indices into BODY_REGIONS of canonical `points` (N, 3) with skinning weights (N, 24) over
    the skeleton `rest_joints` (24, 3), metres, canonical T-pose.

    Each point takes the region whose joints weigh most in its skinning; then a point in a ball of
    ARMPIT_RADIUS under a shoulder is an armpit, a point on the arm's underside (facing down in the T-pose,
    facing the torso once the arm hangs) an inner arm, and a point on the top of a thigh facing the other
    thigh, or between the legs below the hips, the crotch."""
    points, joints = points.double(), rest_joints.double().to(points.device)
    joint_region = _joint_regions().to(points.device)
    totals = torch.zeros(len(points), len(BODY_REGIONS), dtype=torch.float64, device=points.device)
    totals.index_add_(1, joint_region, weights.double().to(points.device))
    regions = totals.argmax(dim=1)
    x, y = points[:, 0], points[:, 1]
    arms = (REGION_INDEX["upper arms"], REGION_INDEX["forearms"])
    for shoulder, wrist, sign in ((16, 20, 1.0), (17, 21, -1.0)):
        out = sign * (x - joints[shoulder, 0])  # how far out from the shoulder joint, along the arm
        on_arm = torch.isin(regions, torch.tensor(arms, device=points.device)) & (sign * x > 0)
        down = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64, device=points.device)
        axis = (joints[wrist] - joints[shoulder]) / (joints[wrist] - joints[shoulder]).norm()
        down = (down - (down @ axis) * axis) / (down - (down @ axis) * axis).norm()
        underside = _radial(points, joints[shoulder], joints[wrist]) @ down > INNER_ARM_COSINE
        reach = sign * (joints[wrist, 0] - joints[shoulder, 0]) - 0.02
        regions[on_arm & underside & (out > 0.05) & (out < reach)] = REGION_INDEX["inner arms"]
        pit = joints[shoulder] + torch.tensor([-sign * 0.02, -0.07, 0.0], dtype=torch.float64, device=points.device)
        in_pit = ((points - pit).norm(dim=1) < ARMPIT_RADIUS) & (y < joints[shoulder, 1] - 0.02)
        regions[in_pit] = REGION_INDEX["armpits"]
    hip_y = 0.5 * (joints[1, 1] + joints[2, 1])
    knee_y = 0.5 * (joints[4, 1] + joints[5, 1])
    thighs = regions == REGION_INDEX["thighs"]
    upper_thigh = thighs & (y > hip_y - CROTCH_THIGH_SHARE * (hip_y - knee_y)) & (y < hip_y + 0.02)
    inward = torch.zeros_like(upper_thigh)
    for hip, knee, sign in ((1, 4, 1.0), (2, 5, -1.0)):
        facing_in = -sign * _radial(points, joints[hip], joints[knee])[:, 0] > 0.7
        inward |= (sign * x > 0) & facing_in
    middle = (x.abs() < CROTCH_HALF_WIDTH) & (y < hip_y + 0.02) & ~thighs
    between = middle & (y < y[middle].min() + CROTCH_DEPTH) if middle.any() else middle
    regions[(upper_thigh & inward) | between] = REGION_INDEX["crotch"]
    return regions
