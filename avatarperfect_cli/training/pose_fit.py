"""A video's poses fitted to its frames with the body fixed: what a pose estimator got wrong by a few degrees
per joint, put right.

`fit_poses_to_masks` fits every frame at once, before any Gaussian is trained (train-initial --refine-poses)
or with a trained avatar's Gaussians as the body (evaluate --refine-poses). Each frame gets an axis-angle
offset (24, 3), the root's included, and a translation offset (3,); Adam minimises, over all frames together,
    silhouette   the silhouette distances of the posed body (`training/silhouette.py`), pixels;
    smoothness   the squared acceleration of the posed points along the video (frame numbers as time), so a
                 limb does not jump between consecutive frames: a pose estimator's errors are nearly
                 independent from frame to frame, a body's motion is not;
    prior        the squared offsets from the given poses, weak: the given pose decides only what the
                 silhouettes and the motion leave open (a twist about a limb's axis, a limb in front of the body).
`fit_poses_to_images` then aligns a trained avatar with each frame's pixels (evaluate --refine-poses): the
render against the image and its alpha against the mask, frame by frame.
"""

from __future__ import annotations

import statistics
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.datasets import VideoDataset
from avatarperfect_cli.datasets.people_snapshot import downscaled_camera
from avatarperfect_cli.render import Camera
from avatarperfect_cli.training.silhouette import SkinnedPoints, silhouette_loss, silhouettes


@dataclass
class PoseFitConfig:
    """Settings of the pose fit to the masks.

    resolution:     longest side of the compared masks, pixels
    points:         body points posed and projected (`SkinnedPoints`)
    contour_pixels: mask-contour pixels per frame in the coverage term (drawn, fixed)
    steps:          Adam steps over all frames
    pose_rate:      Adam step of the axis-angle offsets, radians; transl_rate: of the translations, metres
    smoothness:     loss (pixels) of a posed point accelerating 1 cm per frame², growing with its square
    pose_prior:     loss (pixels) of a joint turned 0.1 rad from its given pose, growing with its square
    transl_prior:   loss (pixels) of a translation 5 cm from its given one, growing with its square
    huber:          pixels beyond which a silhouette distance counts linearly
    """

    resolution: int = 256
    points: int = 2000
    contour_pixels: int = 300
    steps: int = 200
    pose_rate: float = 0.01
    transl_rate: float = 0.003
    smoothness: float = 0.1
    pose_prior: float = 0.05
    transl_prior: float = 0.05
    huber: float = 2.0


@dataclass
class PoseFit:
    """body_pose: (T, 24, 3) axis-angle, radians; transl: (T, 3) metres, world frame; loss and start_loss: the
    fit's data term after and before (mean silhouette distance, pixels, or mean image error)."""

    body_pose: torch.Tensor
    transl: torch.Tensor
    loss: float
    start_loss: float


def acceleration(posed: torch.Tensor, times: torch.Tensor) -> torch.Tensor:
    """(T - 2, ...) second derivative of `posed` (T, ...) sampled at increasing `times` (T,), per time unit²."""
    gaps = (times[1:] - times[:-1]).to(posed.dtype).reshape(-1, *([1] * (posed.dim() - 1)))
    velocity = (posed[1:] - posed[:-1]) / gaps
    return (velocity[1:] - velocity[:-1]) / (0.5 * (gaps[1:] + gaps[:-1]))


class PoseOffsets(torch.nn.Module):
    """Per-frame corrections of a video's poses: axis-angle offsets (T, 24, 3), radians, the root's included,
    and translation offsets (T, 3), metres; `penalty` holds the pose fit's smoothness and prior terms.

    times: (T,) the frames' numbers (time for the smoothness term); zero_mean: each joint's and the
    translation's corrections average to zero over the video, for a fit whose body takes what all frames
    share (a pose estimator's errors average out over a video; a body or an offset that is wrong is wrong in
    every frame, and a correction all frames share would not reach the held-out frames)."""

    def __init__(self, times: torch.Tensor, config: PoseFitConfig, zero_mean: bool = False) -> None:
        super().__init__()
        self.times, self.config, self.zero_mean = times.double(), config, zero_mean
        self.raw_pose = torch.nn.Parameter(torch.zeros(len(times), 24, 3))
        self.raw_transl = torch.nn.Parameter(torch.zeros(len(times), 3))

    @property
    def pose(self) -> torch.Tensor:
        return self.raw_pose - self.raw_pose.mean(dim=0) if self.zero_mean else self.raw_pose

    @property
    def transl(self) -> torch.Tensor:
        return self.raw_transl - self.raw_transl.mean(dim=0) if self.zero_mean else self.raw_transl

    def param_groups(self) -> list[dict]:
        return [{"params": [self.raw_pose], "lr": self.config.pose_rate}, {"params": [self.raw_transl], "lr": self.config.transl_rate}]

    def penalty(self, posed: torch.Tensor) -> torch.Tensor:
        """Smoothness of `posed` (T, P, 3) world points, metres, along the video plus the offsets' prior, pixels."""
        config = self.config
        smooth = acceleration(posed * 100.0, self.times).square().sum(dim=-1).mean() if len(self.times) > 2 else posed.sum() * 0
        prior = (self.pose / 0.1).square().sum(dim=-1).mean() * config.pose_prior
        prior = prior + (self.transl / 0.05).square().sum(dim=-1).mean() * config.transl_prior
        return config.smoothness * smooth + prior

    def applied(self, body_pose: torch.Tensor, transl: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The corrected poses (T, 24, 3) and translations (T, 3), in the dtype of the given ones, detached."""
        with torch.no_grad():
            return (body_pose.float() + self.pose).to(body_pose.dtype), (transl.float() + self.transl).to(transl.dtype)


def fit_poses_to_masks(
    video: VideoDataset, body: SkinnedPoints, config: PoseFitConfig | None = None, on_step: Callable[[], None] | None = None
) -> PoseFit:
    """Every frame's pose and translation fitted to its mask, starting from the video's own (which already
    carry any translation offset). body: the body's points (`SkinnedPoints.of_template` or `.of_avatar`),
    kept fixed; on_step: called after each step (progress)."""
    config = config or PoseFitConfig()
    data = silhouettes(video, torch.arange(len(video)), config.resolution, config.contour_pixels)
    offsets = PoseOffsets(video.frame_ids, config)

    def losses() -> tuple[torch.Tensor, torch.Tensor]:
        posed = body.posed(data.body_pose + offsets.pose, data.transl + offsets.transl)  # (T, P, 3)
        fit = silhouette_loss(posed, data, config.huber).mean()
        return fit + offsets.penalty(posed), fit

    optimizer = torch.optim.Adam(offsets.param_groups())
    with torch.no_grad():
        start_loss = float(losses()[1])
    for _ in range(config.steps):
        optimizer.zero_grad(set_to_none=True)
        losses()[0].backward()
        optimizer.step()
        if on_step is not None:
            on_step()
    with torch.no_grad():
        loss = float(losses()[1])
    return PoseFit(*offsets.applied(video.body_pose, video.transl), loss, start_loss)


@dataclass
class ImagePoseConfig:
    """Settings of the pose fit to the images.

    resolution: longest side of the compared images, pixels
    steps:      Adam steps per frame
    pose_rate:  Adam step of the axis-angle offsets, radians; transl_rate: of the translation, metres
    mask_weight: weight of the alpha-against-mask error beside the colour error (both mean absolute)
    prior:      loss of the offsets, mean of (joint offset / 0.1 rad)² and (translation offset / 5 cm)²
    """

    resolution: int = 1024
    steps: int = 80
    pose_rate: float = 0.005
    transl_rate: float = 0.005
    mask_weight: float = 1.0
    prior: float = 0.01


def fit_poses_to_images(
    avatar: Avatar,
    video: VideoDataset,
    config: ImagePoseConfig | None = None,
    on_frame: Callable[[], None] | None = None,
    other_start: PoseFit | None = None,
) -> PoseFit:
    """Each frame's pose and translation moved so the avatar's render (on white) matches the frame's image
    (its person composited on white) and its alpha the mask, one frame at a time, from the video's poses.
    The avatar stays fixed; on_frame: called after each frame (progress).

    other_start: other poses (T, 24, 3) and translations (T, 3) for the same frames, e.g. `fit_poses_to_masks`'s;
    each frame then starts from whichever of its two poses the image error prefers. A mask fit puts right whole
    limbs that a pose estimator got wrong, but where the mask leaves a limb free (over the torso) it also moves
    limbs that were right: from exact poses it loses 9 dB that this fit wins back only in part."""
    config = config or ImagePoseConfig()
    factor = max(1, round(max(video.camera.width, video.camera.height) / config.resolution))
    camera = downscaled_camera(video.camera, factor)
    poses, transls, losses, start_losses = [], [], [], []
    trainable = [parameter for parameter in avatar.params.values() if parameter.requires_grad]
    for parameter in trainable:  # the avatar stays as it is: no gradients for it
        parameter.requires_grad_(False)
    try:
        for t in range(len(video)):
            frame = _FrameTarget.of(video, t, camera, avatar.device)
            body_pose, transl = video.body_pose[t], video.transl[t]
            if other_start is not None:
                with torch.no_grad():
                    errors = [frame.error(avatar, *start, config.mask_weight) for start in ((body_pose, transl), (other_start.body_pose[t], other_start.transl[t]))]
                    if errors[1] < errors[0]:
                        body_pose, transl = other_start.body_pose[t], other_start.transl[t]
            fit = _fit_frame(avatar, frame, body_pose, transl, config)
            poses.append(fit.body_pose)
            transls.append(fit.transl)
            losses.append(fit.loss)
            start_losses.append(fit.start_loss)
            if on_frame is not None:
                on_frame()
    finally:
        for parameter in trainable:
            parameter.requires_grad_(True)
    return PoseFit(torch.stack(poses), torch.stack(transls), statistics.fmean(losses), statistics.fmean(start_losses))


@dataclass
class _FrameTarget:
    """One frame at the fit's size: its image composited on white (H, W, 3) and its mask (H, W) as coverage."""

    camera: Camera
    target: torch.Tensor
    mask: torch.Tensor

    @classmethod
    def of(cls, video: VideoDataset, t: int, camera: Camera, device: torch.device) -> _FrameTarget:
        size = (camera.height, camera.width)
        mask = F.interpolate(video.masks[t].float()[None, None], size=size, mode="area")[0, 0]
        image = F.interpolate(video.images[t].permute(2, 0, 1)[None], size=size, mode="area")[0]
        target = image.permute(1, 2, 0) * mask[..., None] + (1.0 - mask[..., None])
        return cls(camera, target.to(device), mask.to(device))

    def error(self, avatar: Avatar, body_pose: torch.Tensor, transl: torch.Tensor, mask_weight: float) -> torch.Tensor:
        """Mean absolute colour error of the avatar's render on white plus `mask_weight` times that of its alpha
        against the mask, at pose (24, 3) and translation (3,)."""
        out = render_avatar(avatar, body_pose, transl, self.camera, torch.ones(3))
        return (out.image - self.target).abs().mean() + mask_weight * (out.alpha - self.mask).abs().mean()


def _fit_frame(avatar: Avatar, frame: _FrameTarget, body_pose: torch.Tensor, transl: torch.Tensor, config: ImagePoseConfig) -> PoseFit:
    """The pose (24, 3) and translation (3,) near the given ones that best match `frame`."""
    pose_offset = torch.zeros(24, 3, requires_grad=True)
    transl_offset = torch.zeros(3, requires_grad=True)
    optimizer = torch.optim.Adam(
        [{"params": [pose_offset], "lr": config.pose_rate}, {"params": [transl_offset], "lr": config.transl_rate}]
    )

    def error() -> torch.Tensor:
        prior = (pose_offset / 0.1).square().mean() + (transl_offset / 0.05).square().mean()
        return frame.error(avatar, body_pose + pose_offset, transl + transl_offset, config.mask_weight) + config.prior * prior

    start_loss = 0.0
    for step in range(config.steps):
        optimizer.zero_grad(set_to_none=True)
        loss = error()
        start_loss = float(loss.detach()) if step == 0 else start_loss
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        loss = float(error())
    return PoseFit(body_pose + pose_offset.detach(), transl + transl_offset.detach(), loss, start_loss)
