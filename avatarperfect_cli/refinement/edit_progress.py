"""How far refine took each edit toward its paint.

Inside an edit's mask M_k, the squared colour error of a render against the edit's target (the painted
colours, white where the person painted background) is measured for the image the person painted over and
for the avatar after refine, in the edit's own pose and camera. The share of the way reached is

    share = (error painted over - error now) / error painted over

1 when the render shows the paint, 0 when it is unchanged, negative when it moved away. Below REACHED the
video has won where it and the paint disagree, and refine says so.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.training.trainer import TrainingView

REACHED = 0.5  # an edit is reached when refine went at least this share of the way to its paint


def paint_error(image: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> float:
    """Mean squared colour error of `image` against `target` (both (H, W, 3) in [0, 1]) over the pixels of
    `mask` (H, W) bool and the channels; 0 for an empty mask."""
    if not mask.any():
        return 0.0
    return float(((image.float() - target.float().to(image.device)) ** 2)[mask.to(image.device)].mean())


def rendered_paint_error(avatar: Avatar, view: TrainingView) -> float:
    """`paint_error` of `avatar` rendered over white in the edit `view`'s pose and camera against its target,
    inside its loss mask M_k."""
    view = view.to(avatar.device)
    with torch.no_grad():
        white = torch.ones(3, device=avatar.device)
        image = render_avatar(avatar, view.body_pose, view.transl, view.camera, white).image.clamp(0, 1)
    return paint_error(image, view.image, view.loss_mask)


@dataclass
class EditProgress:
    """An edit's errors inside its mask (`paint_error`): of the image painted over and of the avatar now."""

    number: int
    start_error: float
    error: float

    @property
    def share(self) -> float:
        """The share of the way from the image painted over to the paint (1 when there was nothing to reach)."""
        return 1.0 if self.start_error <= 0.0 else (self.start_error - self.error) / self.start_error

    @property
    def reached(self) -> bool:
        return self.share >= REACHED
