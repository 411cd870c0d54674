"""Additional training (paper §6.3): what `refine` does to the avatar before and while it trains on the video
frames and the edits. Every function here works on tensors and avatars; the stage (stages/refine.py) reads
them from the workspace and writes the result.

Before training:
- the background tool: the Gaussians whose projected centres fall in a new edit's background region, in that
  edit's pose, are deleted (`delete_background`), except, by default, those the video saw at least averagely
  (`seen_by_the_video`);
- the Gaussians the video saw less than average and wider than 5 mm under a new edit's strokes are split in
  two, so the edit has Gaussians as fine as what it paints (`split_barely_seen_under_edits`);
- floaters at the armpits and crotch come from wrong skinning, so every Gaussian's skinning weights move to
  the body template's at its canonical position, and its canonical mean and orientation are re-anchored so
  that the training frames still show it where they did; a Gaussian that re-anchoring cannot keep within
  `template_shift` in every training frame keeps its place and moves toward the template's weights only as
  far as shifts it that much (`pull_toward_template_skinning`, body/template_skinning.py).
Training (`refine_config`) continues on the video frames and the edits: an edit is drawn in a share of the
steps (`edit_step_share`), new edits more often than old ones (`edit_draw_weights`); its loss is masked by
M_k, background pixels of an edit supervise towards the step's random background colour, so Gaussians there
must vanish, and an edit step's loss weighs `EDIT_LOSS_WEIGHT` of a video step's, so an edit repairs what the
video never showed without undoing what it did. Positions and shapes learn slowly, except those of the
Gaussians the video saw less than average: the video hardly constrains them, so they learn at GART's rates
(`barely_seen_rate_scales`). The skinning weights learn from step 0.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.body import BodyTemplate
from avatarperfect_cli.body.template_skinning import (
    bounded_pull_shares,
    largest_shift,
    reanchored_means,
    reanchored_quats,
    template_skin_weights,
)
from avatarperfect_cli.devices import CPU
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.io.pose_json import PoseFile
from avatarperfect_cli.refinement.erase import centres_in_region, delete_gaussians
from avatarperfect_cli.refinement.visibility import painted_visibility
from avatarperfect_cli.training.strategy import DensifyConfig, split_children
from avatarperfect_cli.training.trainer import TrainConfig, TrainingView


# An edit step's loss against a video step's (the paper: 1). One edit drawn in 150 of 500 steps outweighs
# the ~20 video frames that show the same surface, and wherever the avatar's shape differs a little from
# the truth the two disagree: `tall` seed 1's first edit (the back from above) blurred the stripes of every
# back view, -0.52 dB on the training frames. Adam scales each parameter's steps by its own gradients, so
# what only the edits supervise learns as fast at any weight; what the video also supervises follows the
# edit less. That round replayed (training frames / held out / hidden regions, dB): weight 1: -0.52 /
# +0.63 / +0.42; 0.5: -0.39 / +0.69 / +0.50; 0.25: -0.28 / +0.73 / +0.54; 0.1: -0.19 / +0.76 / +0.53; no
# edit: -0.12 / +0.77 / +0.37. Nine five-round study runs at 0.25 against 1: held out +0.10 dB (all nine
# up), worst training round +0.20 dB (all nine up; none past -0.3 dB), hidden regions -0.16 dB (docs/study.md).
EDIT_LOSS_WEIGHT = 0.25


EDIT_STRENGTHS = ("default", "strong")
# A strong edit wins over the video where they disagree (`apply-edit --strength strong`): its loss weighs
# STRONG_LOSS_WEIGHT of a video step's, it is drawn STRONG_DRAWS times as often as a default edit would be
# (on top of the steps the other edits and the video get, up to MAX_EDIT_STEP_SHARE of all steps)
# (`strong_edit_training`), and the Gaussians its strokes show learn positions and shapes at GART's rates, as
# the barely seen ones do, and colours at STRONG_COLOUR_RATE times GART's (`strong_edit_rate_scales`). Adam
# moves a parameter by at most about its rate a step, whatever the weights: at GART's colour rate a blue
# shirt needs about 600 steps to turn magenta, more than a refine has.
STRONG_LOSS_WEIGHT = 1.0
STRONG_DRAWS = 3.0
MAX_EDIT_STEP_SHARE = 0.6
STRONG_COLOUR_RATE = 10.0
COLOUR_PARAMETERS = ("sh_dc", "sh_rest")

# Blend weight over a new edit's strokes, pixels, from which a barely seen Gaussian wider than 5 mm is split in
# two before training (`split_barely_seen_under_edits`): about 1,000 of the ~48,000 Gaussians per edit on
# the 512² study avatars.
SPLIT_PAINTED = 0.1


@dataclass
class RefineSettings:
    """iterations: training steps (the paper: 500); edit_probability: share of steps that draw an edit (0.3;
    the first refine, whose edits are all new, draws `new_edit_share` of that, see `edit_step_share`);
    protect_seen: False deletes every Gaussian whose centre falls in a background stroke (the paper's
    literal rule), True spares the ones the video saw at least averagely (see `seen_by_the_video`);
    new_edit_share: share of the edit draws that go to the edits this run applies for the first time
    (None: every edit equally, as the paper; see `edit_draw_weights`);
    keep_shapes: edit steps leave the Gaussians' scales and rotations alone (`SHAPE_PARAMETERS`): the
    training frames keep their look, at some cost to what the edits repair (docs/refine.md);
    edit_loss_weight: an edit step's loss against a video step's (1: the paper; see `EDIT_LOSS_WEIGHT`);
    barely_seen_rates: when there are edits, the Gaussians the video saw less than average learn positions
    and shapes at GART's rates, the others at refine's (`barely_seen_rate_scales`);
    split_painted: pixels; the barely seen Gaussians wider than 5 mm that a new edit's strokes show with at
    least this much blend weight are split in two first (`split_barely_seen_under_edits`; None: never);
    template_skinning: the largest share of the way each Gaussian's skinning weights move to the body
    template's at its canonical position before training (1: the template's, 0: the learned ones kept);
    template_shift: metres; a Gaussian whose move would shift it further than this in any training frame
    (after re-anchoring) moves only that far (math.inf: no limit);
    reanchor: the canonical means and orientations move with the weights so that the training frames keep
    showing the Gaussians where they did (`pull_toward_template_skinning`);
    smpl_model_dir: the SMPL files, for SMPL avatars;
    device: where the avatar is trained (the result is written from the CPU)."""

    iterations: int = 500
    edit_probability: float = 0.3
    seed: int = 0
    protect_seen: bool = True  # background strokes keep the Gaussians the video saw at least averagely
    new_edit_share: float | None = 0.5
    keep_shapes: bool = False
    edit_loss_weight: float = EDIT_LOSS_WEIGHT
    barely_seen_rates: bool = True
    split_painted: float | None = SPLIT_PAINTED
    template_skinning: float = 1.0
    template_shift: float = 0.003
    reanchor: bool = True
    smpl_model_dir: Path | None = None
    device: torch.device = CPU

    def check(self) -> None:
        """Raise AvatarPerfectError, naming the refine option, for a value out of its range."""
        if self.iterations < 1:
            raise AvatarPerfectError(f"--iterations must be at least 1, got {self.iterations}")
        if not 0.0 <= self.edit_probability <= 1.0:
            raise AvatarPerfectError(f"--edit-probability must be in [0, 1], got {self.edit_probability}")
        if not self.edit_loss_weight > 0.0:
            raise AvatarPerfectError(f"--edit-loss-weight must be positive, got {self.edit_loss_weight:g}")
        if self.new_edit_share is not None and not 0.0 < self.new_edit_share <= 1.0:
            raise AvatarPerfectError(f"--new-edit-share must be in (0, 1], got {self.new_edit_share}")
        if self.split_painted is not None and not self.split_painted > 0.0:
            raise AvatarPerfectError(f"the split threshold must be positive, got {self.split_painted:g} pixels")
        if not 0.0 <= self.template_skinning <= 1.0:
            raise AvatarPerfectError(f"--template-skinning must be in [0, 1], got {self.template_skinning}")
        if not self.template_shift > 0.0:
            raise AvatarPerfectError(f"--template-shift-mm must be positive, got {self.template_shift * 1e3:g}")


def seen_by_the_video(visibility: torch.Tensor) -> torch.Tensor:
    """(N,) bool: Gaussians whose accumulated visibility V ((N,), refinement/visibility.py) is at least its mean.
    The video vouches for them, so a background stroke does not delete them (training can still make them
    transparent in the edit's view): a stroke in a new pose can cover Gaussians that are mis-skinned there but
    right in every training frame, and centres behind the stroke that the video showed (on the 512² sample, a
    32 px stroke over the torso deleted 1140 Gaussians under the literal rule and cost 2.4 dB on the training
    frames)."""
    return visibility >= visibility.mean()


def delete_background(
    avatar: Avatar, regions: Sequence[tuple[PoseFile, torch.Tensor]], protected: torch.Tensor | None = None
) -> tuple[Avatar, torch.Tensor]:
    """Delete the Gaussians whose centres fall, in an edit's pose and camera, in its background region (H, W)
    bool, for each (pose, region) of `regions`, except the `protected` ones ((N,) bool, or None); returns
    (avatar, the deleted ones as (N,) bool)."""
    delete = torch.zeros(len(avatar), dtype=torch.bool, device=avatar.device)
    for pose, region in regions:
        delete |= centres_in_region(avatar, pose, region)
    if protected is not None:
        delete &= ~protected.to(avatar.device)
    return delete_gaussians(avatar, delete), delete


def painted_weight(avatar: Avatar, edits: Sequence[TrainingView]) -> torch.Tensor:
    """(N,) float64: each Gaussian's blend weight summed over the edit views' loss masks M_k, pixels."""
    painted = torch.zeros(len(avatar), dtype=torch.float64, device=avatar.device)
    for edit in edits:
        painted += painted_visibility(avatar, PoseFile(edit.body_pose, edit.transl, edit.camera), edit.loss_mask.double())
    return painted


def split_barely_seen_under_edits(
    avatar: Avatar, seen: torch.Tensor, edits: list[TrainingView], min_painted: float, seed: int
) -> tuple[Avatar, torch.Tensor, int]:
    """Split in two (3DGS's split, `split_children`) every Gaussian that the video saw less than average
    (`seen` (N,) bool False), that the edit views' strokes show (blend weight summed over their loss masks M_k at
    least `min_painted` pixels) and whose largest standard deviation exceeds GART's clone/split size
    (`DensifyConfig.clone_max_scale`, 5 mm). Returns the new avatar, its `seen` (children are barely
    seen) and how many were split.

    An edit can only teach detail as fine as the Gaussians under its strokes, and refine does not densify
    (`refine_config`): the barely seen ones keep the initial fit's sizes, about as wide as the checker
    cells of the sample's hidden regions (docs/study.md)."""
    painted = painted_weight(avatar, edits)
    densify = DensifyConfig()
    large = avatar.params["log_scales"].detach().amax(dim=-1) > math.log(densify.clone_max_scale)
    split = ~seen & (painted >= min_painted) & large
    params = {name: param.detach() for name, param in avatar.params.items()}
    children = split_children(params, split, densify.split_factor, torch.Generator().manual_seed(seed))
    params = {name: torch.cat([param[~split], children[name]]) for name, param in params.items()}
    children_seen = seen.new_zeros(len(children["means"]))
    return avatar.with_params(params), torch.cat([seen[~split], children_seen]), int(split.sum())


# Fixed-point steps of the re-anchoring: the template's weights are read at the re-anchored canonical mean,
# which depends on them. On `default` seed 0's initial avatar (no training; held out / hidden regions /
# training frames, dB): one step 34.55 / 15.41 / 38.304, two 34.64 / 15.56 / 38.303, three 34.65 / 15.57.
REANCHOR_STEPS = 2


def pull_toward_template_skinning(
    avatar: Avatar, template: BodyTemplate, body_pose: torch.Tensor, transl: torch.Tensor, share: float, max_shift: float,
    reanchor: bool = True,
) -> None:
    """Move each Gaussian's skinning weights `share` of the way to the body `template`'s at its canonical mean
    and, if `reanchor`, re-anchor its canonical mean and orientation so that the video's frames (body_pose
    (T, 24, 3), transl (T, 3)) still show it where they did (`reanchored_means`, `reanchored_quats`). A Gaussian
    that re-anchoring would still shift by more than `max_shift` metres in some frame (the frames' poses differ
    by more than a rigid motion there), or every Gaussian without re-anchoring, keeps its mean and orientation
    and moves only as far toward the template's weights as shifts it that much (`bounded_pull_shares`).

    The video fixes where each Gaussian is in its poses, not which bones carry it: in an A-pose turntable a
    point by the armpit skinned to the arm with a canonical mean off the body lands where one skinned to the
    chest on the body does, and only the second follows the body into poses the video never showed. On
    `default` seed 0's initial avatar, before any training: the bounded pull alone held out +0.54 dB, hidden
    regions +0.22 dB, training frames -0.35 dB; re-anchored +1.17, +1.26 and -0.005 dB (docs/refine.md)."""
    means, quats = avatar.params["means"].detach(), avatar.params["quats"].detach()
    transforms = torch.stack([avatar.joint_transforms(pose, offset) for pose, offset in zip(body_pose, transl)])
    learned = avatar.skin_weights.detach()
    weights = learned.clone()
    reanchored = torch.zeros(len(avatar), dtype=torch.bool, device=means.device)
    if reanchor:
        anchored_means = means
        for _ in range(REANCHOR_STEPS):
            target = torch.lerp(learned, template_skin_weights(template, anchored_means), share)
            anchored_means = reanchored_means(means, learned, target, transforms)
        reanchored = largest_shift(means, learned, anchored_means, target, transforms) <= max_shift
        weights[reanchored] = target[reanchored]
        anchored_quats = reanchored_quats(means[reanchored], quats[reanchored], learned[reanchored], target[reanchored], transforms)
        with torch.no_grad():
            avatar.params["means"][reanchored] = anchored_means[reanchored]
            avatar.params["quats"][reanchored] = anchored_quats
    rest = ~reanchored
    if rest.any():
        target = template_skin_weights(template, means[rest])
        shares = bounded_pull_shares(means[rest], learned[rest], target, transforms, share, max_shift)
        weights[rest] = torch.lerp(learned[rest], target, shares[:, None])
    avatar.set_skin_weights(weights)


def edit_draw_weights(edits: Sequence[int], new: set[int], new_share: float | None) -> list[float]:
    """Each edit's relative chance of being drawn, for the edit numbers `edits`: the `new` ones share
    `new_share` of the edit draws, the others the rest (uniform when either group is empty or new_share is
    None). Drawn uniformly, the newest of five edits gets 30 of a 500-step run's steps, too few to learn it."""
    new_count = sum(number in new for number in edits)
    old_count = len(edits) - new_count
    if new_share is None or new_count == 0 or old_count == 0:
        return [1.0] * len(edits)
    return [new_share / new_count if number in new else (1.0 - new_share) / old_count for number in edits]


def strong_edit_training(
    views: Sequence[TrainingView], strong: Sequence[bool], step_share: float, edit_loss_weight: float
) -> tuple[list[TrainingView], float]:
    """The edit `views` (their draw weights set, `edit_draw_weights`) with the `strong` ones' draws multiplied
    by STRONG_DRAWS and their loss by STRONG_LOSS_WEIGHT / `edit_loss_weight`, and the share of steps that draw
    an edit raised so that the other edits keep their draws (at most MAX_EDIT_STEP_SHARE)."""
    total = sum(view.draw_weight for view in views)
    views = [
        replace(view, draw_weight=view.draw_weight * STRONG_DRAWS, loss_weight=STRONG_LOSS_WEIGHT / edit_loss_weight) if is_strong else view
        for view, is_strong in zip(views, strong)
    ]
    if total > 0.0:
        step_share = min(MAX_EDIT_STEP_SHARE, step_share * sum(view.draw_weight for view in views) / total)
    return views, step_share


def edit_step_share(edit_probability: float, new_share: float | None, new_count: int, old_count: int) -> float:
    """Share of a refine's steps that draw an edit: `edit_probability`, except when every edit is new (the
    first refine): then only the new edits' part of it (`new_share`), the rest going to the video, so that
    new edits get as many draws in the first refine as in any later one (`edit_draw_weights`).

    Drawn at the full share, the first edit alone took 150 of the 500 steps, and the first round cost the
    training frames the most: in nine study runs on re-anchored refines, -0.41 dB at worst (`default`
    seed 1), against -0.27 dB (`tall` seed 1) at half the share (docs/study.md, variants tried)."""
    if new_share is not None and new_count > 0 and old_count == 0:
        return edit_probability * new_share
    return edit_probability


# What a new pose's edit reshapes, the training frames see: on `tall`, one edit step in three trained with
# everything cost its training frames 0.24 dB after one refine, and 0.07 dB with these two left alone.
SHAPE_PARAMETERS = ("quats", "log_scales")


# A refinement continues where the initial fit's position schedule ended (1.6e-4 -> 1.6e-6 over 2000
# steps) rather than restarting it at the top, which would shake the fitted Gaussians loose.
REFINE_MEANS_RATE = 1.6e-5
# Scales and rotations learn at 3% of GART's rates. At full rates every 500-step refine stretched more
# Gaussians to fit the training poses, which showed as streaks at bent knees in other poses: on `tall`,
# three video-only refines took 462 -> 944 Gaussians longer than 3 cm and held-out PSNR -0.68 dB; at 10%:
# 556 and -0.08 dB; at 3%: 486 and -0.02 dB. Five study rounds (ap-exact), held-out PSNR change on `tall`:
# -0.41 dB at 100%, +0.25 at 10%, +0.51 at 3%, +0.36 at 1% (`default`: +0.57 at 10%, +0.84 at 3%).
REFINE_SHAPE_RATE_FACTOR = 0.03
# Barely seen Gaussians learn positions at GART's rate (`barely_seen_rate_scales`): 1.6e-4 = 10 x REFINE_MEANS_RATE.
BARELY_SEEN_MEANS_FACTOR = 10.0


def barely_seen_rate_scales(seen: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per-Gaussian factors on refine's position and shape rates (`train`'s rate_scales) that give the
    Gaussians the video saw less than average (`seen` (N,) bool False, see `seen_by_the_video`) GART's
    rates, and leave the others at refine's.

    Refine moves shapes and positions slowly so that the video's Gaussians keep fitting the training
    poses (`REFINE_SHAPE_RATE_FACTOR`). The barely seen ones have little there to keep, and mostly the
    edits tell them what to be: at refine's rates they keep the initial fit's shapes, which can hold no
    more detail than the template's vertex spacing (the armpit's checker, docs/refine.md)."""
    barely = (~seen).float()
    factors = {"means": BARELY_SEEN_MEANS_FACTOR, "quats": 1.0 / REFINE_SHAPE_RATE_FACTOR, "log_scales": 1.0 / REFINE_SHAPE_RATE_FACTOR}
    return {name: 1.0 + (factor - 1.0) * barely for name, factor in factors.items()}


def strong_edit_rate_scales(shown: torch.Tensor, rate_scales: dict[str, torch.Tensor] | None) -> dict[str, torch.Tensor]:
    """`rate_scales` (`train`'s per-Gaussian factors, or None) with the Gaussians a strong edit shows (`shown`
    (N,) bool) learning positions and shapes at least at GART's rates (`barely_seen_rate_scales`) and colours
    at STRONG_COLOUR_RATE times theirs."""
    scales = dict(rate_scales or {})
    for name, factor in barely_seen_rate_scales(~shown).items():
        scales[name] = torch.maximum(scales[name], factor) if name in scales else factor
    for name in COLOUR_PARAMETERS:
        scales[name] = 1.0 + (STRONG_COLOUR_RATE - 1.0) * shown.float()
    return scales


def refine_config(settings: RefineSettings) -> TrainConfig:
    """The training settings of a refinement run: GART's rates over `iterations`, positions from
    REFINE_MEANS_RATE down, scales and rotations at REFINE_SHAPE_RATE_FACTOR of theirs, skinning from
    step 0, and no densification: splitting and pruning at steps 101 and 302 of a 500-step run leave
    too few steps to settle (measured on the 256² sample, 500 video-only steps: -0.33 dB on the
    training frames with densification, +0.21 dB without)."""
    config = TrainConfig(
        iterations=settings.iterations, seed=settings.seed, edit_probability=settings.edit_probability,
        edit_loss_weight=settings.edit_loss_weight,
    )  # fmt: skip
    config.learning_rates.total_steps = settings.iterations
    config.learning_rates.means = REFINE_MEANS_RATE
    config.learning_rates.quats *= REFINE_SHAPE_RATE_FACTOR
    config.learning_rates.log_scales *= REFINE_SHAPE_RATE_FACTOR
    config.learning_rates.skin_start = 0
    config.densify.refine_stop = 0
    if settings.keep_shapes:
        config.edit_frozen = SHAPE_PARAMETERS
    return config
