"""The `refine` stage (paper §6.3): re-optimise the current avatar on the video plus every registered edit.

It reads the avatar, the video and the edits from the workspace, runs the additional training of
refinement/additional_training.py (the background tool for the edits applied for the first time, splitting,
the pull toward the template's skinning, training), and writes the new avatar as ws/avatar/NNN.ply (NNN one
past the highest iteration so far), then commits it by the manifest with the run's settings and counts in its
history entry. The edits an avatar iteration has applied are recorded there, so each edit's background
strokes delete Gaussians once. Every earlier iteration stays; `revert` makes an earlier one current.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

from rich.console import Console

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.io.workspace import locked_workspace
from avatarperfect_cli.refinement.additional_training import (
    SPLIT_PAINTED,
    RefineSettings,
    barely_seen_rate_scales,
    delete_background,
    edit_draw_weights,
    edit_step_share,
    painted_weight,
    pull_toward_template_skinning,
    refine_config,
    seen_by_the_video,
    split_barely_seen_under_edits,
    strong_edit_rate_scales,
    strong_edit_training,
)
from avatarperfect_cli.refinement.edit_progress import EditProgress, rendered_paint_error
from avatarperfect_cli.refinement.visibility import DEFAULT_EDIT_WEIGHT
from avatarperfect_cli.stages.visibility import current_visibility
from avatarperfect_cli.stages.workspace_data import applied_edits, body_template, load_video, registered_edits
from avatarperfect_cli.training.trainer import train, video_views

__all__ = ["RefineSettings", "refine", "revert"]


def refine(workspace_root: Path, settings: RefineSettings | None = None, progress: bool = True) -> Path:
    """Refine the current avatar on the video and every registered edit; returns the new avatar's path."""
    settings = settings or RefineSettings()
    settings.check()
    console = Console(stderr=True, quiet=not progress)
    with locked_workspace(workspace_root) as workspace:
        start = time.perf_counter()
        avatar = Avatar.load(workspace.require_avatar()).to(settings.device)
        edits = registered_edits(workspace)
        done = set(applied_edits(workspace))
        new_edits = [edit for edit in edits if edit.number not in done]
        protect = settings.protect_seen and any(bool(edit.background().any()) for edit in new_edits)
        views = {edit.number: edit.training_view() for edit in edits}
        strong = [edit.strength == "strong" for edit in edits]
        start_errors = {edit.number: edit.painted_over_error for edit in edits}
        for number, error in start_errors.items():
            if error is None:  # registered before the error was recorded: measured from this refine's start
                start_errors[number] = rendered_paint_error(avatar, views[number])
        seen = None
        if edits and (protect or settings.barely_seen_rates or settings.split_painted is not None):
            seen = seen_by_the_video(current_visibility(workspace, avatar, DEFAULT_EDIT_WEIGHT, progress).visibility)
        regions = [(edit.pose, edit.background()) for edit in new_edits]
        avatar, deleted = delete_background(avatar, regions, seen if protect else None)
        seen = None if seen is None else seen.to(avatar.device)[~deleted]
        split = 0
        if seen is not None and settings.split_painted is not None and new_edits:
            avatar, seen, split = split_barely_seen_under_edits(
                avatar, seen, [views[edit.number] for edit in new_edits], settings.split_painted, settings.seed
            )
        rate_scales = barely_seen_rate_scales(seen) if seen is not None and settings.barely_seen_rates else None
        if any(strong):
            shown = painted_weight(avatar, [views[edit.number] for edit, is_strong in zip(edits, strong) if is_strong])
            rate_scales = strong_edit_rate_scales(shown >= SPLIT_PAINTED, rate_scales)
        deleted = int(deleted.sum())
        video = load_video(workspace)
        if settings.template_skinning > 0.0:
            template = body_template(workspace, avatar.body_model, settings.smpl_model_dir)
            pull_toward_template_skinning(
                avatar, template, video.body_pose, video.transl, settings.template_skinning, settings.template_shift, settings.reanchor
            )
        console.print(
            f"refining avatar {workspace.iteration:03d} ({len(avatar):,} Gaussians after deleting {deleted:,} and splitting {split:,}) "
            f"on {len(video)} frames and {len(edits)} edits"
        )
        weights = edit_draw_weights([edit.number for edit in edits], {edit.number for edit in new_edits}, settings.new_edit_share)
        edit_views = [replace(views[edit.number], draw_weight=weight) for edit, weight in zip(edits, weights)]
        step_share = edit_step_share(settings.edit_probability, settings.new_edit_share, len(new_edits), len(edits) - len(new_edits))
        edit_views, step_share = strong_edit_training(edit_views, strong, step_share, settings.edit_loss_weight)
        config = refine_config(replace(settings, edit_probability=step_share))
        train(avatar, video_views(video), edit_views, config, progress=progress, rate_scales=rate_scales)
        reached = [EditProgress(edit.number, start_errors[edit.number], rendered_paint_error(avatar, views[edit.number])) for edit in edits]
        iteration = max(workspace.committed_avatars()) + 1
        path = workspace.avatar_path(iteration)
        avatar.save(path)
        seconds = time.perf_counter() - start
        workspace.commit(
            {
                "stage": "refine",
                "avatar": iteration,
                "from": workspace.iteration,
                "edits": [edit.number for edit in edits],
                "applied_edits": sorted(done | {edit.number for edit in edits}),
                "deleted": deleted,
                "split": split,
                "iterations": settings.iterations,
                "edit_probability": settings.edit_probability,
                "edit_step_share": step_share,
                "new_edit_share": settings.new_edit_share,
                "keep_shapes": settings.keep_shapes,
                "edit_loss_weight": settings.edit_loss_weight,
                "barely_seen_rates": settings.barely_seen_rates,
                "template_skinning": settings.template_skinning,
                "template_shift_mm": settings.template_shift * 1e3,
                "reanchor": settings.reanchor,
                "seed": settings.seed,
                "strong_edits": [edit.number for edit, is_strong in zip(edits, strong) if is_strong],
                "edit_progress": {f"{item.number:03d}": round(item.share, 3) for item in reached},
                "seconds": round(seconds, 1),
                "gaussians": len(avatar),
            },
            iteration,
        )
    console.print(f"wrote {path} ({len(avatar):,} Gaussians, {seconds:.0f} s)")
    for progress_line in progress_lines(workspace_root, reached, strong):
        console.print(progress_line, highlight=False, soft_wrap=True)
    return path


def progress_lines(workspace_root: Path, reached: list[EditProgress], strong: list[bool]) -> list[str]:
    """One line per edit: the share of the way to its paint refine reached inside its mask, and for an edit
    not reached (`EditProgress.reached`) what to do about it."""
    lines = []
    for progress, is_strong in zip(reached, strong):
        line = f"edit {progress.number:03d}{' (strong)' if is_strong else ''}: {progress.share:.0%} of the way to the paint inside its mask"
        if not progress.reached and is_strong:
            line += "; the video still disagrees there: refine again, or paint it in a pose nearer the video's"
        elif not progress.reached:
            line += (
                f"; the video disagrees there and won. If the paint is right: "
                f"avatarperfect apply-edit {workspace_root} --edit {progress.number} --strength strong, then refine"
            )
        lines.append(line)
    return lines


def revert(workspace_root: Path, iteration: int) -> None:
    """Make avatar `iteration` current again; later iterations stay on disk and in the history."""
    with locked_workspace(workspace_root) as workspace:
        if iteration not in workspace.committed_avatars():
            raise AvatarPerfectError(f"{workspace_root}: no avatar iteration {iteration}")
        workspace.require_avatar(iteration)
        workspace.commit({"stage": "revert", "to": iteration}, iteration)
