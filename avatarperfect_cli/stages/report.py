"""The `report` stage: what the refinement loop did, as pictures a person reads.

Writes into an output folder (never into the workspace, but for the evaluations it adds there):
    metrics.png      held-out PSNR and IoU of every avatar iteration (evaluating the missing ones)
    suggestions.png  one row per registered edit: the suggestion, its guide, the painted image, the mask
    comparison.mp4   the held-out video: ground truth | first avatar | current avatar
The folder is checked before any work: these files must not be there yet unless `force`; other files are kept.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from rich.console import Console
from rich.progress import track

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.datasets import load_people_snapshot
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.io import atomic_write_bytes, read_image, write_image
from avatarperfect_cli.io.outputs import check_output_folder
from avatarperfect_cli.io.video import frame_writer
from avatarperfect_cli.io.workspace import Workspace, open_workspace
from avatarperfect_cli.refinement.pictures import figure_png
from avatarperfect_cli.stages.evaluate import evaluate
from avatarperfect_cli.stages.workspace_data import SUGGESTIONS, registered_edits

WHITE = torch.ones(3)
MASK_TINT = torch.tensor([1.0, 0.0, 0.8])
REPORT_FILES = ("metrics.png", "suggestions.png", "comparison.mp4")


def iteration_metrics(workspace_root: Path, test_dataset: Path, progress: bool = True) -> list[dict]:
    """Held-out metrics of every committed avatar iteration in order, evaluating the ones not yet evaluated."""
    workspace = open_workspace(workspace_root)
    name = Path(test_dataset).resolve().name
    results = []
    for iteration in sorted(workspace.committed_avatars()):
        path = workspace.eval_dir(iteration) / name / "metrics.json"
        if not path.is_file():
            evaluate(workspace_root, test_dataset, iteration, progress=progress)
        results.append(json.loads(path.read_text()))
    return results


def metrics_plot(results: list[dict], title: str) -> bytes:
    """PNG bytes: held-out PSNR and IoU against the avatar iteration."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    iterations = [r["iteration"] for r in results]
    figure, (psnr_axis, iou_axis) = plt.subplots(1, 2, figsize=(9, 3.4))
    psnr_axis.plot(iterations, [r["mean"]["psnr"] for r in results], "o-", color="tab:blue")
    psnr_axis.set(xlabel="avatar iteration", ylabel="held-out PSNR (dB)")
    iou_axis.plot(iterations, [r["mean"]["iou"] for r in results], "o-", color="tab:green")
    iou_axis.set(xlabel="avatar iteration", ylabel="held-out IoU")
    for axis in (psnr_axis, iou_axis):
        axis.set_xticks(iterations)
        axis.grid(alpha=0.3)
    return figure_png(figure, title)


def edits_sheet(workspace: Workspace) -> torch.Tensor | None:
    """(R*H, 4*W, 3): per registered edit, its suggestion, guide, painted image and mask (tinted); None without edits."""
    rows = []
    for edit in registered_edits(workspace):
        record = json.loads((edit.folder / "edit.json").read_text())
        number = record["painted_over"].removeprefix("suggestion ")
        suggestion = workspace.root / SUGGESTIONS / number
        if not number.isdigit() or not suggestion.is_dir():
            continue
        suggested = read_image(suggestion / "suggested.png", "RGB")
        painted = read_image(next(edit.folder.glob("edited.*")), "RGB")
        mask = read_image(edit.folder / "mask.png", "L")
        masked = suggested * (1 - 0.6 * mask) + 0.6 * mask * MASK_TINT
        rows.append(torch.cat([suggested, read_image(suggestion / "guide.png", "RGB"), painted, masked], dim=1))
    return torch.cat(rows, dim=0) if rows else None


def report(
    workspace_root: Path, test_dataset: Path, output_dir: Path, fps: float = 10.0, progress: bool = True, force: bool = False
) -> Path:
    """Write REPORT_FILES for the workspace into `output_dir` (see the module doc); nothing there before the work is done."""
    output_dir = Path(output_dir)
    check_output_folder(output_dir, REPORT_FILES, force)
    console = Console(stderr=True, quiet=not progress)
    results = iteration_metrics(workspace_root, test_dataset, progress)
    workspace = open_workspace(workspace_root)
    title = f"{workspace_root}: held-out {Path(test_dataset).resolve().name}"
    sheet = edits_sheet(workspace)
    test = load_people_snapshot(test_dataset, downscale=int(workspace.manifest.get("downscale", 1)))
    if not len(test):
        raise AvatarPerfectError(f"{test_dataset}: no frames")
    first, current = Avatar.load(workspace.require_avatar(0)), Avatar.load(workspace.require_avatar())
    height, width = test.images.shape[1:3]
    with frame_writer(output_dir / "comparison.mp4", 3 * width, height, fps) as write, torch.no_grad():
        for t in track(range(len(test)), description="comparison video", console=console, disable=not progress):
            views = [render_avatar(a, test.body_pose[t], test.transl[t], test.camera, WHITE).image for a in (first, current)]
            write(torch.cat([test.images[t], *views], dim=1))
    atomic_write_bytes(output_dir / "metrics.png", metrics_plot(results, title))
    if sheet is not None:
        write_image(output_dir / "suggestions.png", sheet)
    console.print(f"wrote metrics.png, {'suggestions.png, ' if sheet is not None else ''}comparison.mp4 in {output_dir}")
    for result in results:
        mean = result["mean"]
        console.print(f"  avatar {result['iteration']:03d}: PSNR {mean['psnr']:.2f} dB, IoU {mean['iou']:.4f}, SSIM {mean['ssim']:.4f}")
    return output_dir
