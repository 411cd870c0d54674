"""Body and camera pose suggestion (paper §6.2): show the user what the video saw least.

Minimises  sum_i clip(V_i - mean V) * r_i * sigma(G, D(z), tau)_i  over a latent body pose z (decoded by
a natural-pose prior D) and an orbit camera tau = (azimuth, elevation) around the posed body. The sum
is the sum of a one-channel image whose per-Gaussian colour is clip(V_i - mean V) * r_i (the weight
image), so it is differentiable through the rasterizer; the camera enters as a rigid transform of the
posed Gaussians (the rasterizer's camera itself carries no gradient), which is the same image.

r_i = min(1, E_i / mean E) is how much animations show Gaussian i (`exposure_relevance`): E_i is its mean
visibility over `exposure_poses` random natural poses seen from the dataset camera's height. This is not
in the paper (r = 1, `exposure_poses=0`): the paper's objective weighs every barely-seen Gaussian alike,
so it spends rounds on the soles and the top of the head, which the video never saw and animations
hardly show (docs/study.md: on `default`, three of five suggestions showed the soles).

The camera keeps the dataset camera's intrinsics and up direction; azimuth 0 / elevation 0 is the
dataset camera's own viewing direction. Its distance is set from the posed body each step so that the
whole body fits in `fill` of the image: the objective cannot be won by zooming in. The distance is
part of the gradient (a pose that widens the body pushes the camera back and shows everything smaller).

Devices: the search variables (latent, angles), the pose prior and the collision capsules stay on the
CPU (a few dozen numbers); the decoded pose, the orbit and every render follow the avatar's device.
Suggestions (pose files) are on the CPU.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.body import posed_joints
from avatarperfect_cli.io.pose_json import PoseFile
from avatarperfect_cli.refinement.collision import BodyCapsules
from avatarperfect_cli.refinement.pose_prior import PosePrior
from avatarperfect_cli.refinement.visibility import suggestion_weights
from avatarperfect_cli.render import Camera, rasterization
from avatarperfect_cli.render.camera import MAX_MAGNIFICATION, framing_distance, rotation_about
from avatarperfect_cli.training.optim import Adam

BODY_POSE_MODES = ("optimise", "canonical", "random")
EXPOSURE_SEED_OFFSET = 7919  # animation_exposure's random stream: seed + this
SUGGEST_ADAM_EPS = 1e-8  # torch.optim.Adam's default: z and the angles are O(1), unlike the Gaussians' parameters


@dataclass
class SuggestConfig:
    """Settings of one suggestion.

    body_pose:   "optimise" (z and camera), "canonical" (the training pose, camera only: the paper's
                 baseline) or "random" (a random natural pose and camera, no optimisation: the control)
    starts:      optimisation starts, the best kept; chosen as the best of `candidates` random
                 cameras (and, when optimising the pose, random natural poses), scored forward only
    steps:       Adam steps per start
    resolution:  longest image side while optimising, pixels (the result is rendered at full size)
    fill:        share of the image the posed body may span
    max_magnification: no body part may look more than this many times larger than at the body's centre
                 (the camera backs off): at 512² a `tall` search put a raised foot 2.4x closer to the
                 camera than the hips, and the picture was one blurred shoe (docs/suggest.md)
    max_elevation_deg: the camera stays within this angle above or below the dataset camera's horizon;
                 at 45° most searches ended on the band's edge, showing the soles from below or the top
                 of the head from above, which animations seldom show (docs/suggest.md)
    min_separation_deg: a start must look from at least this far from earlier suggestions' cameras
    exposure_poses: random natural poses that measure how much animations show each Gaussian (the
                 relevance r of the module doc); 0 gives the paper's objective (r = 1)
    """

    body_pose: str = "optimise"
    starts: int = 3
    candidates: int = 24
    steps: int = 30
    resolution: int = 128
    fill: float = 0.9
    max_magnification: float = MAX_MAGNIFICATION
    max_elevation_deg: float = 20.0
    min_separation_deg: float = 30.0
    latent_learning_rate: float = 0.12
    angle_learning_rate: float = 0.06
    collision_weight: float = 1e4
    exposure_poses: int = 32
    seed: int = 0


@dataclass
class Suggestion:
    """A suggested view: the pose JSON's content plus how it was found.

    pose:      body_pose (24, 3), transl (3,) and the full-size camera
    latent:    (32,) z of the body pose
    azimuth, elevation: orbit angles, radians, relative to the dataset camera
    objective: sum_i clip(V_i - mean V) * r_i * sigma_i at full size (lower shows more of the barely seen)
    """

    pose: PoseFile
    latent: torch.Tensor
    azimuth: float
    elevation: float
    objective: float


class FramedView(NamedTuple):
    """The body posed and turned for one orbit view: means (N, 3) metres and quats (N, 4) in the world frame
    of `camera` (the rendering camera, on the avatar's device), and the view's pose file (CPU)."""

    means: torch.Tensor
    quats: torch.Tensor
    camera: Camera
    pose: PoseFile


class OrbitView:
    """Poses the avatar by a latent z and views it from orbit angles, with automatic framing.

    reference: the training pose (its body_pose's global orientation and its transl are kept) and the
    dataset camera (intrinsics, up direction, azimuth 0).
    """

    def __init__(
        self, avatar: Avatar, prior: PosePrior, reference: PoseFile, fill: float, max_magnification: float = MAX_MAGNIFICATION
    ) -> None:
        self.avatar, self.prior, self.reference = avatar, prior, reference
        self.fill, self.max_magnification = fill, max_magnification
        self.device = avatar.device
        rotation = reference.camera.world_to_camera[:3, :3].float().to(self.device)
        self.base_rotation = rotation
        self.right, self.up, self.forward = rotation[0], -rotation[1], rotation[2]

    def body_pose(self, latent: torch.Tensor) -> torch.Tensor:
        return self.prior.decode(latent[None])[0]

    def orbit(self, azimuth: torch.Tensor, elevation: torch.Tensor) -> torch.Tensor:
        """(3, 3) world rotation of the camera on the avatar's device: tilt by `elevation` (positive: from
        above), then turn by `azimuth` about the up axis (0-d angles on any device)."""
        azimuth, elevation = azimuth.to(self.device), elevation.to(self.device)
        return rotation_about(self.up, azimuth) @ rotation_about(self.right, -elevation)

    def frame(self, latent: torch.Tensor, azimuth: torch.Tensor, elevation: torch.Tensor, camera: Camera) -> FramedView:
        """Pose the body by `latent`, turn it by the orbit angles and frame it: what `render` rasterizes, and
        the view's pose file. Differentiable w.r.t. latent and the angles. `camera` gives the intrinsics and size."""
        body_pose = self.body_pose(latent)
        transl = self.reference.transl
        transforms = self.avatar.joint_transforms(body_pose, transl)
        center = self._body_center(transforms.detach())
        orbit = self.orbit(azimuth, elevation)
        world = torch.eye(4, device=self.device)
        world[:3, :3] = orbit.T  # turning the body by orbit^T = turning the camera by orbit
        world[:3, 3] = center - orbit.T @ center
        means, quats = self.avatar.skin(world @ transforms)
        distance = framing_distance(
            means - center, self.base_rotation, camera.K, camera.width, camera.height, self.fill, self.max_magnification
        )
        base = self._camera(center, float(distance.detach()), camera)
        # the camera sits at the detached distance; moving the body by the difference (zero in value) lets
        # the gradient see that a pose which widens the body pushes the camera back
        means = means + (distance - distance.detach()) * self.forward
        with torch.no_grad():
            view_rotation = self.base_rotation @ orbit.detach().T
            eye = center + orbit.detach() @ (base.center.float() - center)
            view = torch.eye(4, device=self.device)
            view[:3, :3] = view_rotation
            view[:3, 3] = -view_rotation @ eye
        view_camera = Camera(camera.K, view.cpu(), camera.width, camera.height)
        return FramedView(means, quats, base, PoseFile(body_pose.detach().clone(), transl.clone(), view_camera))

    def render(
        self, latent: torch.Tensor, azimuth: torch.Tensor, elevation: torch.Tensor, camera: Camera, colors: torch.Tensor
    ) -> tuple[torch.Tensor, PoseFile]:
        """The (H, W, C) image of per-Gaussian `colors` (N, C, on the avatar's device) on black, on the
        avatar's device, and the pose file of the view (on the CPU). Differentiable as `frame`."""
        framed = self.frame(latent, azimuth, elevation, camera)
        out = rasterization(framed.means, framed.quats, self.avatar.scales, self.avatar.opacities, colors, framed.camera)
        return out.image, framed.pose

    def _body_center(self, transforms: torch.Tensor) -> torch.Tensor:
        """(3,) centre of the bounding box of the joints posed by `transforms` (24, 4, 4), metres."""
        joints = posed_joints(transforms, self.avatar.rest_joints)
        return 0.5 * (joints.min(dim=0).values + joints.max(dim=0).values)

    def _camera(self, center: torch.Tensor, distance: float, camera: Camera) -> Camera:
        eye = center - distance * self.forward
        view = torch.eye(4, device=self.device)
        view[:3, :3] = self.base_rotation
        view[:3, 3] = -self.base_rotation @ eye
        return Camera(camera.K.float().to(self.device), view, camera.width, camera.height)


def animation_exposure(
    view: OrbitView, prior: PosePrior, capsules: BodyCapsules, camera: Camera, poses: int, seed: int
) -> torch.Tensor:
    """E: (N,) float64 mean visibility (pixels at `camera`'s size) of every Gaussian over `poses` random
    collision-free natural poses (the reference pose where a draw collides), each seen from a random
    azimuth at the dataset camera's height and framed as the search frames it. Its own random stream, so
    the search draws the same starts with or without it."""
    generator = torch.Generator().manual_seed(seed + EXPOSURE_SEED_OFFSET)
    total = torch.zeros(len(view.avatar), dtype=torch.float64, device=view.device)
    with torch.no_grad():
        for _ in range(poses):
            latent = prior.sample_latent(generator)
            if capsules.intersecting_pairs(view.body_pose(latent)):
                latent = prior.initial_latent()
            azimuth = torch.tensor(2 * math.pi * float(torch.rand((), generator=generator)))
            framed = view.frame(latent, azimuth, torch.tensor(0.0), camera)
            # the framed Gaussians seen by the framing camera: the pose file's view, skinned once
            no_colors = framed.means.new_zeros(len(framed.means), 1)
            out = rasterization(framed.means, framed.quats, view.avatar.scales, view.avatar.opacities, no_colors, framed.camera)
            total += out.visibility.double()
    return total / poses


def exposure_relevance(exposure: torch.Tensor) -> torch.Tensor:
    """r = min(1, E / mean E), (N,): every Gaussian animations show at least averagely counts fully."""
    return (exposure / exposure.mean().clamp_min(1e-30)).clamp_max(1.0)


def _angle_between_views(first: Camera, second: Camera) -> float:
    """Angle, degrees, between two cameras' viewing directions."""
    cosine = float(first.world_to_camera[2, :3].double() @ second.world_to_camera[2, :3].double())
    return math.degrees(math.acos(max(-1.0, min(1.0, cosine))))


def suggest_view(
    avatar: Avatar,
    visibility: torch.Tensor,
    prior: PosePrior,
    capsules: BodyCapsules,
    reference: PoseFile,
    config: SuggestConfig | None = None,
    earlier: Sequence[PoseFile] = (),
    on_step: Callable[[], None] = lambda: None,
) -> Suggestion:
    """The body pose and camera that best show the Gaussians the video saw least.

    visibility: (N,) accumulated V; reference: training pose + dataset camera (full size);
    earlier: pose files of earlier suggestions (their cameras are avoided by `min_separation_deg`);
    on_step: called once per optimisation step (progress).
    """
    config = config or SuggestConfig()
    if config.body_pose not in BODY_POSE_MODES:
        raise ValueError(f"body_pose must be one of {BODY_POSE_MODES}, got {config.body_pose!r}")
    generator = torch.Generator().manual_seed(config.seed)
    view = OrbitView(avatar, prior, reference, config.fill, config.max_magnification)
    full = reference.camera
    small = full.scaled(min(1.0, config.resolution / max(full.width, full.height)))
    weights = suggestion_weights(visibility).float()[:, None].to(avatar.device)
    if config.exposure_poses:
        exposure = animation_exposure(view, prior, capsules, small, config.exposure_poses, config.seed)
        weights = weights * exposure_relevance(exposure).float()[:, None]
    scale = float(weights.abs().max()) or 1.0
    weights = weights / scale  # the search works on weights in [-1, 0]; `_finish` reports in V's units

    def objective(latent: torch.Tensor, azimuth: torch.Tensor, elevation: torch.Tensor, camera: Camera):
        image, pose = view.render(latent, azimuth, elevation, camera, weights)
        return image.sum() * (full.width / camera.width) ** 2, pose

    max_elevation = math.radians(config.max_elevation_deg)

    def random_camera() -> tuple[float, float]:
        azimuth = 2 * math.pi * float(torch.rand((), generator=generator))
        sine = math.sin(max_elevation) * (2 * float(torch.rand((), generator=generator)) - 1)  # uniform on the band
        return azimuth, math.asin(sine)

    def random_natural_latent() -> torch.Tensor:
        for _ in range(20):
            latent = prior.sample_latent(generator)
            if not capsules.intersecting_pairs(view.body_pose(latent).detach()):
                return latent
        return prior.initial_latent()

    canonical = prior.initial_latent()
    if config.body_pose == "random":
        latent = random_natural_latent()
        azimuth, elevation = random_camera()
        return _finish(view, latent, azimuth, elevation, full, objective, scale)

    def separated(pose: PoseFile) -> bool:
        return all(_angle_between_views(pose.camera, e.camera) >= config.min_separation_deg for e in earlier)

    candidates = []
    with torch.no_grad():
        for index in range(config.candidates):
            azimuth, elevation = random_camera()
            optimise_pose = config.body_pose == "optimise" and index % 2 == 1
            latent = random_natural_latent() if optimise_pose else canonical.clone()
            value, pose = objective(latent, torch.tensor(azimuth), torch.tensor(elevation), small)
            candidates.append((not separated(pose), float(value), latent, azimuth, elevation))
    candidates.sort(key=lambda c: (c[0], c[1]))

    best: tuple[float, torch.Tensor, float, float] | None = None
    for too_close, start_value, latent, azimuth, elevation in candidates[: config.starts]:
        result = _optimise(view, capsules, objective, separated, latent, azimuth, elevation, small, config, max_elevation, on_step)
        result = result or (math.inf if too_close else start_value, latent, azimuth, elevation)
        if best is None or result[0] < best[0]:
            best = result
    assert best is not None
    return _finish(view, best[1], best[2], best[3], full, objective, scale)


def _optimise(view, capsules, objective, separated, latent, azimuth, elevation, camera, config, max_elevation, on_step):
    """Adam on (z, azimuth, elevation) from one start; the best iterate that is collision-free and looks from
    at least `min_separation_deg` away from earlier suggestions (`separated(pose)`), as (objective, latent,
    azimuth, elevation), or None when there was none."""
    latent = latent.clone().requires_grad_(config.body_pose == "optimise")
    angles = torch.tensor([azimuth, elevation], requires_grad=True)
    groups = [{"params": [angles], "lr": config.angle_learning_rate}]
    if config.body_pose == "optimise":
        groups.append({"params": [latent], "lr": config.latent_learning_rate})
    optimizer = Adam(groups, eps=SUGGEST_ADAM_EPS)
    variables = [variable for group in groups for variable in group["params"]]
    best = None
    for _ in range(config.steps):
        value, pose = objective(latent, angles[0], angles[1], camera)
        penalty = capsules.penetration(view.body_pose(latent)[None])[0]
        current = float(value.detach())
        if float(penalty.detach()) == 0.0 and (best is None or current < best[0]) and separated(pose):
            best = (current, latent.detach().clone(), float(angles[0].detach()), float(angles[1].detach()))
        loss = value / camera.width / camera.height + config.collision_weight * penalty.to(value.device)
        # the search's own variables only: a plain backward would also fill every avatar parameter's gradient
        for variable, gradient in zip(variables, torch.autograd.grad(loss, variables)):
            variable.grad = gradient
        optimizer.step()
        with torch.no_grad():
            angles[1].clamp_(-max_elevation, max_elevation)
        on_step()
    return best


def _finish(
    view: OrbitView, latent, azimuth: float, elevation: float, camera: Camera, objective, weight_scale: float
) -> Suggestion:
    with torch.no_grad():
        value, pose = objective(latent, torch.tensor(azimuth), torch.tensor(elevation), camera)
    return Suggestion(pose, latent.detach().clone(), azimuth % (2 * math.pi), elevation, float(value) * weight_scale)
