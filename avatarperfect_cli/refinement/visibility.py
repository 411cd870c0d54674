"""Gaussian visibility (paper §6.2): how much of each Gaussian the video and the edits showed.

v_i^I = sum over the pixels p of image I of T_i^p * alpha_i^p, the weight Gaussian i gets in the
alpha blend (in pixels: a fully visible Gaussian covering 10 pixels has visibility 10), and

    V = (1 - w) * mean over the video frames of sigma + w * mean over the edit views of sigma

with w = 0.01 in the paper. Without edit views V is the video mean alone.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.io.pose_json import PoseFile
from avatarperfect_cli.render import rasterization

DEFAULT_EDIT_WEIGHT = 0.01
BARELY_SEEN = 0.1  # a Gaussian seen less than this share of the mean visibility is barely seen


def gaussian_visibility(avatar: Avatar, view: PoseFile, world_transform: torch.Tensor | None = None) -> torch.Tensor:
    """sigma(G, theta, tau): (N,) float64 visibility of every Gaussian in one posed view, pixels, on the
    avatar's device (the view may live on any device).

    world_transform: optional (4, 4) rigid transform applied to the posed avatar (see `Avatar.pose`).
    """
    with torch.no_grad():
        means, quats = avatar.pose(view.body_pose, view.transl, world_transform)
        out = rasterization(
            means, quats, avatar.scales, avatar.opacities, means.new_zeros(len(avatar), 1), view.camera
        )
    return out.visibility.double()


def painted_visibility(avatar: Avatar, view: PoseFile, pixel_weight: torch.Tensor) -> torch.Tensor:
    """(N,) float64: sum over the pixels p of pixel_weight[p] * T_i^p * alpha_i^p, each Gaussian's visibility
    counted over the weighted pixels only (pixel_weight (H, W), e.g. an edit's mask M_k), on the avatar's
    device.

    The blend weight T_i^p * alpha_i^p is the derivative of pixel p's colour with respect to Gaussian i's
    colour, so one backward pass through a one-channel render gives the sum on either backend."""
    with torch.no_grad():
        means, quats = avatar.pose(view.body_pose, view.transl)
        scales, opacities = avatar.scales, avatar.opacities
    colors = torch.zeros(len(avatar), 1, dtype=means.dtype, device=means.device, requires_grad=True)
    with torch.enable_grad():
        image = rasterization(means, quats, scales, opacities, colors, view.camera).image
        (image[..., 0] * pixel_weight.to(image)).sum().backward()
    return colors.grad[:, 0].double()


def mean_visibility(avatar: Avatar, views: Iterable[PoseFile]) -> tuple[torch.Tensor, int]:
    """(N,) float64 mean of sigma over `views` (on the avatar's device), and how many views there were
    (zeros for none)."""
    total = torch.zeros(len(avatar), dtype=torch.float64, device=avatar.device)
    count = 0
    for view in views:
        total += gaussian_visibility(avatar, view)
        count += 1
    return total / max(count, 1), count


def combine_visibility(video_mean: torch.Tensor, edit_mean: torch.Tensor | None, edit_weight: float) -> torch.Tensor:
    """V from the video's and the edits' mean visibilities (N,); `edit_mean` None when there are no edits."""
    if edit_mean is None:
        return video_mean
    return (1.0 - edit_weight) * video_mean + edit_weight * edit_mean


def accumulate_visibility(
    avatar: Avatar, video: Sequence[PoseFile], edits: Sequence[PoseFile] = (), edit_weight: float = DEFAULT_EDIT_WEIGHT
) -> torch.Tensor:
    """V: (N,) float64 accumulated visibility over the video frames and the edit views (see module doc)."""
    video_mean, _ = mean_visibility(avatar, video)
    edit_mean = mean_visibility(avatar, edits)[0] if edits else None
    return combine_visibility(video_mean, edit_mean, edit_weight)


def suggestion_weights(visibility: torch.Tensor) -> torch.Tensor:
    """(N,) clip(V_i - mean V) = min(V_i - mean V, 0): negative for the Gaussians seen less than average,
    the per-Gaussian colour of the one-channel image whose sum is the suggestion objective."""
    return (visibility - visibility.mean()).clamp_max(0.0)


def barely_seen(visibility: torch.Tensor, share_of_mean: float = BARELY_SEEN) -> torch.Tensor:
    """(N,) bool: Gaussians the video saw less than `share_of_mean` of the mean visibility."""
    return visibility < share_of_mean * visibility.mean()

