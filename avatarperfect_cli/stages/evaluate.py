"""The `evaluate` stage: IoU, PSNR and SSIM of an avatar on held-out frames (paper §7.3).

IoU compares the rendered silhouette (accumulated opacity > 0.5) with the ground-truth mask; PSNR
and SSIM compare the render on white with the ground truth on white. With `refine_poses` each held-out
frame's pose is first fitted to that frame with the avatar fixed (the field's test-time pose refinement),
and both scores are reported: the given poses' and the refined poses'.
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path

import torch
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, track
from rich.table import Table

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.datasets import FrameRange, VideoDataset, load_people_snapshot
from avatarperfect_cli.devices import CPU
from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.io import atomic_write_text, write_image
from avatarperfect_cli.io.atomic import atomic_folder
from avatarperfect_cli.io.outputs import check_writable_folder
from avatarperfect_cli.io.workspace import MANIFEST, Workspace, open_workspace, reading_workspace
from avatarperfect_cli.stages.workspace_data import training_camera, transl_offset
from avatarperfect_cli.training import metrics
from avatarperfect_cli.training.pose_fit import PoseFitConfig, fit_poses_to_images, fit_poses_to_masks
from avatarperfect_cli.training.silhouette import SkinnedPoints, check_masks

WHITE = torch.ones(3)
GRID_ROWS = 6


def comparison_grid(rows: list[tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
    """Stack rows of (ground truth | render | error x4) images (H, W, 3) into one (R*H, 3*W, 3) image."""
    return torch.cat(
        [torch.cat([truth, render, ((render - truth).abs() * 4).clamp(0, 1)], dim=1) for truth, render in rows], dim=0
    )


def evaluate(
    workspace_root: Path,
    test_dataset: Path,
    iteration: int | None = None,
    frames: FrameRange | None = None,
    progress: bool = True,
    poses: str = "auto",
    device: torch.device = CPU,
    refine_poses: bool = False,
) -> dict:
    """Evaluate avatar `iteration` (default: the latest) on `test_dataset`, at the training resolution.

    The avatar is rendered on `device`; each render comes back to the CPU, where the metrics are computed.

    The test video's poses: "auto" (poses/anim_nerf_test.npz, else poses_optimized.npz, else poses.npz) or a
    pose file relative to the test dataset; their translations move by the workspace's transl_offset
    (the test poses come from the same fitting as the training ones).
    The test video is downscaled by the training video's factor and must then have the training size;
    another resolution is refused (one line) rather than scored at a different size.
    Writes ws/eval/NNN/<test folder name>/metrics.json (per frame and mean) and comparison.png; with
    `refine_poses` also the refined poses' scores (metrics.json's "refined_poses") and comparison_refined.png.
    Returns the metrics.

    A committed avatar never changes, so the scoring needs no lock and runs beside a stage that holds one;
    the lock is taken only to write the results, when it is free (see `reading_workspace`).
    """
    return _evaluate(open_workspace(workspace_root), test_dataset, iteration, frames, progress, poses, device, refine_poses)


def _evaluate(
    workspace: Workspace, test_dataset: Path, iteration: int | None, frames: FrameRange | None, progress: bool, poses: str,
    device: torch.device, refine_poses: bool,
) -> dict:  # fmt: skip
    avatar = Avatar.load(workspace.require_avatar(iteration)).to(device)
    out_dir = workspace.eval_dir(iteration) / Path(test_dataset).resolve().name
    check_writable_folder(out_dir.parent)
    trained = training_camera(workspace)
    downscale = _training_downscale(workspace)
    test = load_people_snapshot(test_dataset, frames, "test", downscale, pose_source=poses)
    test.transl = test.transl + transl_offset(workspace)
    if progress:
        for note in test.notes:
            Console(stderr=True, soft_wrap=True).print(note, markup=False, highlight=False)
    if (test.camera.width, test.camera.height) != (trained.width, trained.height):
        raise InputFileError(
            test_dataset,
            f"its frames are {test.camera.width}x{test.camera.height} after the training downscale of {downscale}, but "
            f"the avatar was trained at {trained.width}x{trained.height}; evaluate on a video of the training resolution",
        )
    if not len(test):
        raise AvatarPerfectError(f"{test_dataset}: no frames to evaluate")
    if refine_poses:
        check_masks(test)
    per_frame, grid = _score(avatar, test, test.body_pose, test.transl, progress)
    result = {
        "iteration": workspace.iteration if iteration is None else iteration,
        "test_dataset": str(Path(test_dataset).resolve()),
        "poses": test.pose_file,
        "frames": len(per_frame),
        "mean": _mean(per_frame),
        "per_frame": per_frame,
    }
    pictures = {"comparison.png": grid}
    if refine_poses:
        body_pose, transl = refined_test_poses(avatar, test, progress)
        refined_frames, pictures["comparison_refined.png"] = _score(avatar, test, body_pose, transl, progress)
        result["refined_poses"] = {"mean": _mean(refined_frames), "per_frame": refined_frames}
    with reading_workspace(workspace.root), atomic_folder(out_dir) as staging:
        atomic_write_text(staging / "metrics.json", json.dumps(result, indent=2) + "\n")
        for name, picture in pictures.items():
            write_image(staging / name, picture)
    if progress:
        table = Table(title=f"avatar {result['iteration']:03d} on {len(per_frame)} frames of {out_dir.name}")
        for name in ("poses", "IoU", "PSNR (dB)", "SSIM"):
            table.add_column(name, justify="right")
        rows = [("given", result["mean"])] + ([("refined", result["refined_poses"]["mean"])] if refine_poses else [])
        for label, mean in rows:
            table.add_row(label, f"{mean['iou']:.4f}", f"{mean['psnr']:.2f}", f"{mean['ssim']:.4f}")
        Console(stderr=True).print(table)
        Console(stderr=True).print(f"wrote {out_dir / 'metrics.json'} and {' and '.join(pictures)}")
    return result


def refined_test_poses(avatar: Avatar, test: VideoDataset, progress: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """The test frames' poses (T, 24, 3) and translations (T, 3) fitted to their masks, then to their images,
    with the avatar fixed (training/pose_fit.py); each frame's image fit starts from its given pose or its mask
    fit, whichever matches its image better.

    Each frame is fitted on its own, without the smoothness along the video that the training fit uses: held-out
    frames need not be a clip sampled densely enough for it (the synthetic subjects' held-out motion moves
    15 cm per frame, and the smoothness term dragged its 3°-noisy poses from 5 to 13 cm off the truth)."""
    config = PoseFitConfig(smoothness=0.0)
    with Progress(TextColumn("[bold]fitting the test poses"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=Console(stderr=True), transient=True, disable=not progress) as bar:  # fmt: skip
        task = bar.add_task("masks", total=config.steps + len(test))
        to_masks = fit_poses_to_masks(test, SkinnedPoints.of_avatar(avatar, config.points), config, lambda: bar.advance(task))
        to_images = fit_poses_to_images(avatar, test, on_frame=lambda: bar.advance(task), other_start=to_masks)
    return to_images.body_pose, to_images.transl


def _score(
    avatar: Avatar, test: VideoDataset, body_pose: torch.Tensor, transl: torch.Tensor, progress: bool
) -> tuple[list[dict], torch.Tensor]:
    """Per-frame IoU, PSNR and SSIM of the avatar at the given poses (T, 24, 3) and translations (T, 3), and
    the comparison grid of every few frames."""
    per_frame, grid_rows = [], []
    grid_every = max(1, len(test) // GRID_ROWS)
    with torch.no_grad():
        for t in track(range(len(test)), description="evaluating", console=Console(stderr=True), disable=not progress):
            out = render_avatar(avatar, body_pose[t], transl[t], test.camera, WHITE)
            render, alpha = out.image.clamp(0, 1).cpu(), out.alpha.cpu()
            per_frame.append(
                {
                    "frame": int(test.frame_ids[t]),
                    "iou": metrics.iou(alpha > 0.5, test.masks[t]),
                    "psnr": metrics.psnr(render, test.images[t]),
                    "ssim": metrics.ssim(render, test.images[t]),
                }
            )
            if t % grid_every == 0 and len(grid_rows) < GRID_ROWS:
                grid_rows.append((test.images[t], render))
    return per_frame, comparison_grid(grid_rows)


def _mean(per_frame: list[dict]) -> dict[str, float]:
    return {key: statistics.fmean(frame[key] for frame in per_frame) for key in ("iou", "psnr", "ssim")}


def _training_downscale(workspace: Workspace) -> int:
    """The integer factor the training images were downscaled by (1 when the manifest does not say)."""
    downscale = workspace.manifest.get("downscale", 1)
    if not isinstance(downscale, int) or isinstance(downscale, bool) or downscale < 1:
        raise InputFileError(workspace.root / MANIFEST, f"'downscale' must be a positive integer, got {downscale!r}")
    return downscale
