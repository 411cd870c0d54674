"""Deleting Gaussians selected in a 2D region of a posed view.

- The background tool (paper §6.1) and SuperSplat's Erase Center delete the Gaussians whose projected
  centres fall inside the region.
- SuperSplat's Erase Splat (as the paper's study implemented it) deletes the Gaussians whose
  visibility T * alpha exceeds 0.01 at any pixel of the region.
"""

from __future__ import annotations

import torch

from avatarperfect_cli.avatar.model import PARAMETER_NAMES, Avatar
from avatarperfect_cli.io.pose_json import PoseFile
from avatarperfect_cli.render.cpu import max_weight_in_region
from avatarperfect_cli.render.projection import project_gaussians

ERASE_MODES = ("center", "splat")
SPLAT_VISIBILITY = 0.01


def centres_in_region(avatar: Avatar, view: PoseFile, region: torch.Tensor) -> torch.Tensor:
    """(N,) bool on the avatar's device: Gaussians in front of the camera whose projected centre lies in a
    pixel of `region` (H, W) bool, the pixel that contains it (pixel x covers [x, x + 1))."""
    with torch.no_grad():
        means, _ = avatar.pose(view.body_pose, view.transl)
        camera = view.camera.to(device=means.device, dtype=means.dtype)
        local = means @ camera.world_to_camera[:3, :3].T + camera.world_to_camera[:3, 3]
        depth = local[:, 2]
        in_front = depth > 1e-6
        safe = torch.where(in_front, depth, torch.ones_like(depth))
        pixels = (local[:, :2] / safe[:, None]) @ camera.K[:2, :2].T + camera.K[:2, 2]
    height, width = region.shape
    column, row = torch.floor(pixels[:, 0]), torch.floor(pixels[:, 1])
    on_image = in_front & (column >= 0) & (column < width) & (row >= 0) & (row < height)
    selected = torch.zeros(len(avatar), dtype=torch.bool, device=means.device)
    index = on_image.nonzero()[:, 0]
    selected[index] = region.to(means.device)[row[index].long(), column[index].long()]
    return selected


def splats_in_region(avatar: Avatar, view: PoseFile, region: torch.Tensor, threshold: float = SPLAT_VISIBILITY) -> torch.Tensor:
    """(N,) bool: Gaussians whose blending weight T * alpha exceeds `threshold` at some pixel of `region`."""
    with torch.no_grad():
        means, quats = avatar.pose(view.body_pose, view.transl)
        projection = project_gaussians(means, quats, avatar.scales, avatar.opacities, view.camera.to(dtype=means.dtype))
        weights = max_weight_in_region(
            projection.means2d, projection.conics, avatar.opacities, projection.extents, projection.depths,
            projection.drawn, region,
        )  # fmt: skip
    return weights > threshold


def select_in_region(avatar: Avatar, view: PoseFile, region: torch.Tensor, mode: str) -> torch.Tensor:
    """(N,) bool selection of erase `mode` ("center" or "splat") in `view`'s `region` (H, W) bool."""
    if mode == "center":
        return centres_in_region(avatar, view, region)
    if mode == "splat":
        return splats_in_region(avatar, view, region)
    raise ValueError(f"erase mode must be one of {ERASE_MODES}, got {mode!r}")


def delete_gaussians(avatar: Avatar, delete: torch.Tensor) -> Avatar:
    """A new avatar without the Gaussians where `delete` (N,) bool is set."""
    keep = ~delete
    params = {name: avatar.params[name].detach()[keep] for name in PARAMETER_NAMES}
    return avatar.with_params(params)
