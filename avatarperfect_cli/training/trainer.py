"""The training loop, shared by initial fitting (video only) and refinement (video + painted edits).

Each step draws a view (an edit with probability `edit_probability`, else a video frame), poses the
avatar, renders it over a random background colour, and takes an Adam step on L1 + λ(1 − SSIM) over
the subject's bounding box (edits: masked by the edit mask M_k, paper §6.3, plus the alpha of their
background pixels; the whole edit loss weighed by `edit_loss_weight`). Densification lives in the
strategy object's hooks, so the loop holds no bookkeeping of its own.

Training runs on the avatar's device (`Avatar.to`): the views are moved there once, the background
colours are drawn by the CPU generator (the same colours on every device) and moved there.
"""

from __future__ import annotations

import random
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.datasets import VideoDataset
from avatarperfect_cli.datasets.backdrop import estimate_backdrop
from avatarperfect_cli.render import Camera
from avatarperfect_cli.training.losses import (
    DATASET_BACKGROUND, BandPixels, band_pixels, boundary_band, image_loss, mask_band_supervision, subject_bbox,
)  # fmt: skip
from avatarperfect_cli.training.optim import LearningRates, create_optimizers, set_learning_rates
from avatarperfect_cli.training.pose_refinement import PoseRefiner
from avatarperfect_cli.training.progress import TrainingProgress
from avatarperfect_cli.training.strategy import DensifyConfig, DensifyStrategy


@dataclass
class TrainingView:
    """One supervising image.

    image:      (H, W, 3) target colours in [0, 1] (composited on white)
    foreground: (H, W) bool, where the subject is; elsewhere the target is the background colour
    body_pose:  (24, 3) SMPL axis-angle, joint 0 = global orientation; transl: (3,) metres
    camera:     the view's camera
    loss_mask:  (H, W) bool edit mask M_k, or None to supervise every pixel (video frames)
    draw_weight: relative chance of this edit among the edits when a step draws one
    loss_weight: factor on this edit's loss, on top of `TrainConfig.edit_loss_weight`
    filmed:     (H, W, 3) uint8 a video frame as filmed, and backdrop: (H, W, 3) float32 what lies behind
                its subject, NaN where unknown (`mask_band_supervision`); or None: `image` over white
    """

    image: torch.Tensor
    foreground: torch.Tensor
    body_pose: torch.Tensor
    transl: torch.Tensor
    camera: Camera
    loss_mask: torch.Tensor | None = None
    draw_weight: float = 1.0
    loss_weight: float = 1.0
    filmed: torch.Tensor | None = None
    backdrop: torch.Tensor | None = None

    def to(self, device: torch.device, moved: dict[int, torch.Tensor] | None = None) -> TrainingView:
        """The view with every tensor (the camera's too) on `device`. moved: the backdrops already on `device`,
        by the id of the original, filled as it goes: a backdrop every frame shares is copied once."""
        moved = {} if moved is None else moved
        if self.backdrop is not None and id(self.backdrop) not in moved:
            moved[id(self.backdrop)] = self.backdrop.to(device)
        backdrop = None if self.backdrop is None else moved[id(self.backdrop)]
        loss_mask, filmed = (None if t is None else t.to(device) for t in (self.loss_mask, self.filmed))
        return TrainingView(
            self.image.to(device), self.foreground.to(device), self.body_pose.to(device), self.transl.to(device),
            self.camera.to(device=device), loss_mask, self.draw_weight, self.loss_weight, filmed, backdrop,
        )  # fmt: skip


@dataclass
class TrainConfig:
    """Settings of one training run (GART's defaults for people; DESIGN.md "Avatar fitting")."""

    iterations: int = 2000
    seed: int = 0
    ssim_weight: float = 0.1
    bbox_margin: int = 20
    sh_degree_interval: int = 500  # raise the rendered SH degree by one every this many steps
    edit_probability: float = 0.3
    edit_frozen: tuple[str, ...] = ()  # parameters (Avatar.params names) that edit steps leave unchanged
    # weight of an edit's background pixels' alpha in its loss (`background_alpha`): the colour loss alone
    # pushes a Gaussian out only as hard as its colour differs from the step's background. On the 512²
    # sample's background edit (refine at full shape rates) the stroke's largest alpha after refine was
    # 0.057 without it, 0.046 with 4.
    background_alpha_weight: float = 4.0
    # factor on an edit step's whole loss (1: the paper). Adam scales each parameter's steps by the size of
    # its own gradients, so a Gaussian only the edits supervise learns them as fast at any factor, while one
    # the video supervises too follows the edits that much less.
    edit_loss_weight: float = 1.0
    # pixels either side of a video frame's mask edge where the frame's colours, not the mask, decide what
    # is subject (`mask_band_supervision`; 0: the mask decides everywhere). Masks from segmenters and chroma
    # keys err by about 3 px there (docs/avatar-quality.md).
    mask_band: int = 3
    learning_rates: LearningRates = field(default_factory=LearningRates)
    densify: DensifyConfig = field(default_factory=DensifyConfig)


def video_views(video: VideoDataset) -> list[TrainingView]:
    """One TrainingView per frame of a loaded video (no loss mask: every pixel supervises). With the frames
    as filmed, each view carries its frame and the video's backdrop (`estimate_backdrop`) for the mask band."""
    views = [
        TrainingView(video.images[t], video.masks[t], video.body_pose[t], video.transl[t], video.camera)
        for t in range(len(video))
    ]
    if video.filmed is not None and len(video):
        backdrop = estimate_backdrop(video.filmed, video.masks)
        for view, filmed in zip(views, video.filmed):
            view.filmed, view.backdrop = filmed, backdrop
    return views


def background_alpha(alpha: torch.Tensor, loss_mask: torch.Tensor, foreground: torch.Tensor) -> torch.Tensor:
    """Alpha summed over an edit's background pixels (inside M_k, not foreground), divided by the pixel
    count of `alpha` (H, W), as L1 averages: the term that makes the Gaussians there vanish."""
    return (alpha * (loss_mask & ~foreground)).sum() / alpha.numel()


def _supervised_region(view: TrainingView, margin: int) -> tuple[slice, slice]:
    return subject_bbox(view.foreground if view.loss_mask is None else view.loss_mask, margin)


def _band_pixels(view: TrainingView, region: tuple[slice, slice], width: int) -> BandPixels:
    """The `band_pixels` of a video view's mask band of `width` pixels, inside its loss `region`."""
    rows, cols = region
    frame = view.image[rows, cols] if view.filmed is None else view.filmed[rows, cols].float() / 255
    backdrop = DATASET_BACKGROUND if view.backdrop is None else view.backdrop[rows, cols]
    return band_pixels(boundary_band(view.foreground, width)[rows, cols], frame, backdrop)


def _fixed_pose_transforms(avatar: Avatar, views: Sequence[TrainingView]) -> list[torch.Tensor]:
    """Each view's (24, 4, 4) joint transforms, computed once: the poses and `rest_joints` stay fixed during
    training (forward kinematics is a few dozen small operations, which on a GPU cost more than the
    skinning itself)."""
    with torch.no_grad():
        return [avatar.joint_transforms(view.body_pose, view.transl) for view in views]


def train(
    avatar: Avatar,
    video: Sequence[TrainingView],
    edits: Sequence[TrainingView] = (),
    config: TrainConfig | None = None,
    progress: bool = True,
    pose_refiner: PoseRefiner | None = None,
    rate_scales: Mapping[str, torch.Tensor] | None = None,
) -> Avatar:
    """Optimise `avatar` in place on the video frames and edits, on the avatar's device; returns it.

    rate_scales: optional per-Gaussian (N,) factors on the learning rates of named parameters
    (`Avatar.params` names).
    pose_refiner: optional per-frame pose offsets of the video (one per entry of `video`), optimised
    along with the avatar; read the result with `pose_refiner.refined(...)`. It must live on the
    avatar's device.
    """
    config = config or TrainConfig()
    if not video:
        raise ValueError("training needs at least one video frame")
    device = avatar.device
    moved_backdrops: dict[int, torch.Tensor] = {}
    video = [view.to(device, moved_backdrops) for view in video]
    edits = [view.to(device, moved_backdrops) for view in edits]
    torch.manual_seed(config.seed)
    chooser = random.Random(config.seed)
    rates = config.learning_rates
    optimizers = create_optimizers(avatar.params, rates, row_scales=rate_scales)
    strategy = DensifyStrategy(config.densify, seed=config.seed)
    state = strategy.initialize_state()
    regions = [_supervised_region(view, config.bbox_margin) for view in video]
    edit_regions = [_supervised_region(view, config.bbox_margin) for view in edits]
    bands = [_band_pixels(view, region, config.mask_band) for view, region in zip(video, regions)] if config.mask_band else []
    video_transforms = None if pose_refiner is not None else _fixed_pose_transforms(avatar, video)
    edit_transforms = _fixed_pose_transforms(avatar, edits)
    edit_weights = [view.draw_weight for view in edits]
    with TrainingProgress(config.iterations, enabled=progress) as bar:
        for step in range(config.iterations):
            if step > 0 and step % config.sh_degree_interval == 0:
                avatar.active_sh_degree = min(avatar.active_sh_degree + 1, avatar.sh_degree)
            set_learning_rates(optimizers, rates, step)
            transforms = None
            frozen: tuple[str, ...] = ()
            if edits and chooser.random() < config.edit_probability:
                index = chooser.choices(range(len(edits)), edit_weights)[0]
                view, (rows, cols) = edits[index], edit_regions[index]
                body_pose, transl = view.body_pose, view.transl
                transforms = edit_transforms[index]
                frozen = config.edit_frozen
            else:
                index = chooser.randrange(len(video))
                view, (rows, cols) = video[index], regions[index]
                body_pose, transl = view.body_pose, view.transl
                if pose_refiner is not None:
                    body_pose, transl = pose_refiner.pose(index, body_pose, transl, step)
                else:
                    transforms = video_transforms[index]
            background = torch.rand(3).to(device)
            target = torch.where(view.foreground[rows, cols, None], view.image[rows, cols], background)
            out = render_avatar(avatar, body_pose, transl, view.camera, background, region=(rows, cols), transforms=transforms)
            mask = None if view.loss_mask is None else view.loss_mask[rows, cols]
            image = out.image[rows, cols]
            if mask is None and bands:
                image, target = mask_band_supervision(image, out.alpha[rows, cols], background, target, bands[index])
            loss = image_loss(image, target, mask, config.ssim_weight)
            if mask is not None and config.background_alpha_weight:
                loss = loss + config.background_alpha_weight * background_alpha(out.alpha[rows, cols], mask, view.foreground[rows, cols])

            strategy.step_pre_backward(avatar.params, optimizers, state, step, out)
            (loss if mask is None else config.edit_loss_weight * view.loss_weight * loss).backward()  # the bar shows the unweighted loss
            for name, optimizer in optimizers.items():
                if name not in frozen:
                    optimizer.step()
                optimizer.zero_grad(set_to_none=True)
            if pose_refiner is not None and mask is None:
                pose_refiner.step(index, step)
            strategy.step_post_backward(avatar.params, optimizers, state, step, out)
            bar.update(loss=loss.detach(), image=image.detach(), target=target, count=len(avatar))
    return avatar
