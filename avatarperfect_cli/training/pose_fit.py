"""The video's poses fitted to its masks, every frame at once, with the body fixed: what a pose estimator got
wrong by a few degrees per joint, the silhouettes and the motion's smoothness put right before any Gaussian
is trained.

Each frame gets an axis-angle offset (24, 3), the root's included, and a translation offset (3,); Adam
minimises, over all frames together,
    silhouette   the silhouette distances of the posed template (`training/silhouette.py`), pixels;
    smoothness   the squared acceleration of the posed template points along the video (frame numbers as
                 time), so a limb does not jump between consecutive frames: a pose estimator's errors are
                 nearly independent from frame to frame, a body's motion is not;
    prior        the squared offsets from the given poses, weak: the given pose decides only what the
                 silhouettes and the motion leave open (a twist about a limb's axis, a limb in front of the body).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from avatarperfect_cli.body import BodyTemplate, forward_kinematics, skin_points
from avatarperfect_cli.datasets import VideoDataset
from avatarperfect_cli.training.silhouette import silhouette_loss, silhouettes, surface_points


@dataclass
class PoseFitConfig:
    """Settings of the pose fit.

    resolution:     longest side of the compared masks, pixels
    points:         template vertices posed and projected (drawn by surface area, fixed)
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
    mean silhouette distance over the frames after and before the fit, pixels."""

    body_pose: torch.Tensor
    transl: torch.Tensor
    loss: float
    start_loss: float


def acceleration(posed: torch.Tensor, times: torch.Tensor) -> torch.Tensor:
    """(T - 2, ...) second derivative of `posed` (T, ...) sampled at increasing `times` (T,), per time unit²."""
    gaps = (times[1:] - times[:-1]).to(posed.dtype).reshape(-1, *([1] * (posed.dim() - 1)))
    velocity = (posed[1:] - posed[:-1]) / gaps
    return (velocity[1:] - velocity[:-1]) / (0.5 * (gaps[1:] + gaps[:-1]))


def fit_poses_to_masks(
    video: VideoDataset,
    template: BodyTemplate,
    config: PoseFitConfig | None = None,
    on_step: Callable[[], None] | None = None,
) -> PoseFit:
    """Every frame's pose and translation fitted to its mask, starting from the video's own (which already
    carry any translation offset). template: the body (fitted or exact), kept fixed; on_step: called after
    each step (progress)."""
    config = config or PoseFitConfig()
    frames = torch.arange(len(video))
    data = silhouettes(video, frames, config.resolution, config.contour_pixels)
    chosen = surface_points(template.vertices.float(), template.faces, config.points)
    points, weights = template.vertices[chosen].float(), template.weights[chosen].float()
    rest_joints = template.rest_joints.float()
    times = video.frame_ids.double()
    pose_offsets = torch.zeros_like(data.body_pose, requires_grad=True)
    transl_offsets = torch.zeros_like(data.transl, requires_grad=True)

    def losses() -> tuple[torch.Tensor, torch.Tensor]:
        transforms = forward_kinematics(data.body_pose + pose_offsets, rest_joints, data.transl + transl_offsets)
        posed = skin_points(points, weights, transforms)  # (T, P, 3)
        fit = silhouette_loss(posed, data, config.huber).mean()
        smooth = acceleration(posed * 100.0, times).square().sum(dim=-1).mean() if len(video) > 2 else fit * 0
        prior = (pose_offsets / 0.1).square().sum(dim=-1).mean() * config.pose_prior
        prior = prior + (transl_offsets / 0.05).square().sum(dim=-1).mean() * config.transl_prior
        return fit + config.smoothness * smooth + prior, fit

    optimizer = torch.optim.Adam(
        [{"params": [pose_offsets], "lr": config.pose_rate}, {"params": [transl_offsets], "lr": config.transl_rate}]
    )
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
    body_pose = (video.body_pose.float() + pose_offsets.detach()).to(video.body_pose.dtype)
    transl = (video.transl.float() + transl_offsets.detach()).to(video.transl.dtype)
    return PoseFit(body_pose, transl, loss, start_loss)
