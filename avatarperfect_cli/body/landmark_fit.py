"""Fit per-frame SMPL 24-joint poses of a body template to 2-D and 3-D body landmarks.

Inputs are per SMPL joint (see `prepare.py` for how MediaPipe's 33 BlazePose landmarks map onto them):
where each joint appears in the image, how sure the detector is, and a root-relative 3-D estimate in the
camera's axes whose scale and depth may be off (MediaPipe's world landmarks are about 15 % small and
their depths about half as deep as they should be). The 2-D targets carry the fit; the 3-D ones only
give the directions of the limbs and the torso (which way a limb points towards or away from the camera,
which way the body faces), so their scale does not matter.

All frames are fitted at once with Adam on: robust reprojection error, limb-direction cosine error, the
silhouette's top and bottom rows (the posed template's highest and lowest points must reach them: both
are skin, so this fixes the body's size in the image, hence its depth, which the landmarks' own
proportions would bias), a pose prior that keeps unobserved joints (spine, neck, collars, hands) near
rest, an upright prior, and temporal smoothness of the joint positions. The bone lengths may scale a
little per group while fitting (not returned), so a landmark skeleton with other proportions than the
template's does not fold the limbs towards the camera. Root orientations are optimised as rotation
matrices (continuous 6-D form), so a body turning through half a turn has no axis-angle wrap-around;
they start from the rotation that best aligns the template's torso with the 3-D torso, and the
translations from a linear least-squares fit of the torso to the 2-D targets.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from avatarperfect_cli.body.base import NUM_JOINTS, SMPL_PARENTS, BodyTemplate
from avatarperfect_cli.body.skeleton import forward_kinematics, skin_points
from avatarperfect_cli.render import Camera
from avatarperfect_cli.rotations import matrix_to_axis_angle, rotation_6d_to_matrix

# Bones whose 3-D directions are compared (SMPL joint pairs): legs, arms, hip and shoulder lines, torso.
DIRECTION_BONES = ((1, 4), (4, 7), (2, 5), (5, 8), (16, 18), (18, 20), (17, 19), (19, 21), (1, 2), (16, 17), (0, 12))
TORSO = (1, 2, 16, 17)  # hips and shoulders: the root orientation and translation start from them
# Prior weight per joint on its axis-angle: joints the landmarks do not pin down stay near rest.
_PRIOR = torch.full((NUM_JOINTS,), 0.02)
_PRIOR[[3, 6, 9]] = 0.5  # spine
_PRIOR[[12, 15]] = 0.3  # neck, head
_PRIOR[[13, 14, 22, 23]] = 2.0  # collars, hands
_PRIOR[[10, 11]] = 0.3  # feet
_PRIOR[0] = 0.0  # the root orientation is free
# Bone groups whose lengths scale together while fitting (index = the bone's child joint; left and right
# share a group): the landmarks' skeleton has other proportions than the template's, and a bone too long or
# too short for its landmarks would otherwise fold towards or away from the camera to fit them.
_BONE_GROUP = (-1, 0, 0, 1, 2, 2, 1, 3, 3, 1, 4, 4, 5, 6, 6, 7, 8, 8, 9, 9, 10, 10, 11, 11)
# (root) hips, spine, thighs, shins, feet, neck, collars, head, shoulders, upper arms, forearms, hands
_BONE_GROUPS = 12
# The silhouette's top and bottom are the head, the feet or the hands: their vertices (at most this many,
# evenly strided) stand for the posed template's extremes.
EXTREMITY_JOINTS = (7, 8, 10, 11, 15, 20, 21, 22, 23)
EXTREMITY_POINTS = 400


@dataclass
class JointTargets:
    """What the landmarks say about each SMPL joint, for T frames.

    image:      (T, 24, 2) pixels where the joint appears
    confidence: (T, 24) in [0, 1]; 0 for a joint no landmark observes
    world:      (T, 24, 3) root-relative 3-D positions in the camera's axes (x right, y down, z forward),
                any scale; only directions between joints are used
    rows:       (T, 2) the person's silhouette's top and bottom pixel rows (edges, pixels; NaN where the
                frame cuts the person off), or None
    """

    image: torch.Tensor
    confidence: torch.Tensor
    world: torch.Tensor
    rows: torch.Tensor | None = None


@dataclass
class LandmarkFitConfig:
    """steps / learning_rate: Adam; robust_pixels: reprojection errors beyond this many pixels (at 256
    pixels image height, scaled with it) count less (Geman-McClure); the weights balance the terms;
    lean_weight: the prior that the body's root stands upright relative to a level camera (the root's up
    axis has no component along the viewing direction): a lean towards or away from the camera changes a
    silhouette little, and small vertical biases of the landmarks would otherwise tilt the body;
    proportion_weight: the prior (on squared log scale) that keeps the bone groups' lengths near the
    template's; the fitted lengths are not returned, only the joint rotations; silhouette_weight: the
    top and bottom rows (squared pixel error over robust_pixels squared, like a landmark)."""

    steps: int = 400
    learning_rate: float = 0.03
    robust_pixels: float = 8.0
    direction_weight: float = 0.5
    prior_weight: float = 1.0
    smooth_weight: float = 1.0
    lean_weight: float = 1.0
    proportion_weight: float = 10.0
    silhouette_weight: float = 1.0


def fit_poses(
    template: BodyTemplate, camera: Camera, targets: JointTargets, config: LandmarkFitConfig | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """body_pose (T, 24, 3) axis-angle (joint 0 the global orientation) and transl (T, 3) metres, in the
    camera's world frame, that pose `template` onto `targets`."""
    config = config or LandmarkFitConfig()
    rest = template.rest_joints.double()
    image, confidence, world = targets.image.double(), targets.confidence.double(), targets.world.double()
    world_to_camera = camera.world_to_camera.double()
    roots = _initial_root_rotations(rest, world, confidence)  # (T, 3, 3), camera axes
    transl = _initial_translations(rest, roots, image, confidence, camera)  # camera frame
    # Everything is solved in the camera frame and moved to the world frame at the end.
    root_6d = roots[..., :2].clone().requires_grad_(True)
    local = torch.zeros(len(image), NUM_JOINTS - 1, 3, dtype=torch.float64, requires_grad=True)
    transl = transl.clone().requires_grad_(True)
    log_scales = torch.zeros(_BONE_GROUPS, dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.Adam([root_6d, local, transl, log_scales], lr=config.learning_rate)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: 0.1 ** (step / config.steps))
    K = camera.K.double()
    scale = config.robust_pixels * camera.height / 256.0
    prior = _PRIOR.double()[1:, None]
    points, weights = _extremity_points(template)
    for _ in range(config.steps):
        rotations = rotation_6d_to_matrix(root_6d)
        joints, transforms = _posed(_scaled_skeleton(rest, log_scales), rotations, local, transl)
        pixels = _project(joints, K)
        squared = ((pixels - image) ** 2).sum(-1) / scale**2
        reprojection = (confidence * squared / (squared + 1.0)).sum() / confidence.sum().clamp_min(1.0)
        direction = _direction_error(joints, world, confidence)
        pose_prior = (prior * local**2).sum() / len(image)
        smooth = ((joints[1:] - joints[:-1]) ** 2).sum(-1).mean() if len(image) > 1 else joints.new_zeros(())
        lean = (rotations[:, 2, 1] ** 2).mean()  # the root's up axis (column 1) along the camera's z
        silhouette = joints.new_zeros(())
        if targets.rows is not None:
            rows = _project(skin_points(points, weights, transforms), K)[..., 1]
            extremes = torch.stack([-torch.logsumexp(-rows, dim=1), torch.logsumexp(rows, dim=1)], dim=1)  # soft min, max
            known = ~torch.isnan(targets.rows)
            misses = torch.where(known, extremes - targets.rows.double().nan_to_num(), 0.0)
            silhouette = (misses**2).sum() / known.sum().clamp_min(1) / scale**2
        loss = (
            reprojection + config.direction_weight * direction + config.prior_weight * pose_prior
            + config.smooth_weight * smooth + config.lean_weight * lean
            + config.proportion_weight * (log_scales**2).mean() + config.silhouette_weight * silhouette
        )  # fmt: skip
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        schedule.step()
    with torch.no_grad():
        rotations = rotation_6d_to_matrix(root_6d)
        # camera frame -> world frame: x_w = R^T (x_c - t); the root joint sits at rest pelvis + transl.
        rotation_cw, shift = world_to_camera[:3, :3].T, world_to_camera[:3, 3]
        root_world = (rest[0] + transl - shift) @ rotation_cw.T
        body_pose = torch.cat([matrix_to_axis_angle(rotation_cw @ rotations)[:, None], local], dim=1)
        return body_pose.float(), (root_world - rest[0]).float()


def _extremity_points(template: BodyTemplate) -> tuple[torch.Tensor, torch.Tensor]:
    """Canonical vertices (P, 3) mostly skinned to EXTREMITY_JOINTS, and their weights (P, 24), float64."""
    chosen = torch.isin(template.weights.argmax(dim=1), torch.tensor(EXTREMITY_JOINTS)).nonzero()[:, 0]
    chosen = chosen[:: max(1, len(chosen) // EXTREMITY_POINTS)]
    return template.vertices[chosen].double(), template.weights[chosen].double()


def _scaled_skeleton(rest: torch.Tensor, log_scales: torch.Tensor) -> torch.Tensor:
    """(24, 3) rest joints with each bone (joint minus parent) scaled by exp(log_scales[its group]); the
    root stays where it is."""
    groups = torch.tensor(_BONE_GROUP[1:])
    parents = torch.tensor(SMPL_PARENTS[1:])
    bones = (rest[1:] - rest[parents]) * torch.exp(log_scales[groups])[:, None]
    return _ANCESTRY.to(rest.dtype) @ torch.cat([rest[:1], bones])


def _ancestry() -> torch.Tensor:
    """(24, 24) with entry (j, k) = 1 when joint k is j or one of its ancestors: joints = ancestry @ bones."""
    ancestry = torch.eye(NUM_JOINTS)
    for joint in range(1, NUM_JOINTS):
        ancestry[joint] += ancestry[SMPL_PARENTS[joint]]
    return ancestry


_ANCESTRY = _ancestry()


def _posed(
    rest: torch.Tensor, roots: torch.Tensor, local: torch.Tensor, transl: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Joints (T, 24, 3) and skinning transforms (T, 24, 4, 4) of the skeleton `rest` posed by root rotation
    matrices `roots` (T, 3, 3) about the rest pelvis, local axis-angles (T, 23, 3) and `transl` (T, 3)."""
    body_pose = torch.cat([torch.zeros_like(local[:, :1]), local], dim=1)
    unrooted = forward_kinematics(body_pose, rest, torch.zeros_like(transl))
    root = torch.zeros(len(roots), 4, 4, dtype=roots.dtype)
    root[:, :3, :3] = roots
    root[:, :3, 3] = rest[0] - (roots @ rest[0]) + transl
    root[:, 3, 3] = 1.0
    transforms = root[:, None] @ unrooted
    joints = (transforms[:, :, :3, :3] @ rest[None, :, :, None])[..., 0] + transforms[:, :, :3, 3]
    return joints, transforms


def _project(points: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(..., 2) pixels of camera-frame points (..., 3)."""
    projected = points @ K.T
    return projected[..., :2] / projected[..., 2:].clamp_min(1e-3)


def _direction_error(joints: torch.Tensor, world: torch.Tensor, confidence: torch.Tensor) -> torch.Tensor:
    """Mean over DIRECTION_BONES of confidence-weighted (1 - cosine) between the posed and the 3-D bones."""
    start, end = (torch.tensor(index) for index in zip(*DIRECTION_BONES))
    ours = F.normalize(joints[:, end] - joints[:, start], dim=-1)
    theirs = F.normalize(world[:, end] - world[:, start], dim=-1)
    weight = torch.minimum(confidence[:, end], confidence[:, start])
    return (weight * (1.0 - (ours * theirs).sum(-1))).sum() / weight.sum().clamp_min(1.0)


def _initial_root_rotations(rest: torch.Tensor, world: torch.Tensor, confidence: torch.Tensor) -> torch.Tensor:
    """(T, 3, 3) rotations that best align the rest torso (TORSO joints, centred) with the 3-D torso
    (weighted Kabsch); the 3-D torso is scaled to the rest torso's size first."""
    torso = list(TORSO)
    source = rest[torso] - rest[torso].mean(0)
    weights = confidence[:, torso].clamp_min(1e-3)[..., None]
    target = world[:, torso] - (weights * world[:, torso]).sum(1, keepdim=True) / weights.sum(1, keepdim=True)
    covariance = (weights * target).transpose(1, 2) @ source  # (T, 3, 3): sum w t s^T
    u, _, vh = torch.linalg.svd(covariance)
    sign = torch.sign(torch.linalg.det(u @ vh))
    correction = torch.diag_embed(torch.stack([torch.ones_like(sign), torch.ones_like(sign), sign], dim=-1))
    return u @ correction @ vh


def _initial_translations(
    rest: torch.Tensor, roots: torch.Tensor, image: torch.Tensor, confidence: torch.Tensor, camera: Camera
) -> torch.Tensor:
    """(T, 3) camera-frame translations that put the rotated rest torso on its 2-D targets: for each torso
    joint P = R (J - J0) + J0, (u - cx)(P_z + t_z) = fx (P_x + t_x) and likewise for v, solved linearly."""
    torso = list(TORSO)
    K = camera.K.double()
    points = (rest[torso] - rest[0]) @ roots.transpose(1, 2) + rest[0]  # (T, 4, 3)
    rows, rhs = [], []
    for axis in (0, 1):
        offset = image[:, torso, axis] - K[axis, 2]  # (T, 4)
        focal = K[axis, axis]
        row = torch.zeros(*offset.shape, 3, dtype=torch.float64)
        row[..., axis] = -focal
        row[..., 2] = offset
        rows.append(row)
        rhs.append(focal * points[..., axis] - offset * points[..., 2])
    weight = confidence[:, torso].clamp_min(1e-3).repeat(1, 2)[..., None]
    matrix, target = torch.cat(rows, dim=1) * weight, torch.cat(rhs, dim=1)[..., None] * weight
    return torch.linalg.lstsq(matrix, target).solution[..., 0]
