"""The `report` stage: what the refinement loop did, as pictures a person reads.

Writes into an output folder (never into the workspace, but for the evaluations it adds there):
    metrics.png      held-out PSNR, IoU and SSIM of every avatar iteration (evaluating the missing ones)
    suggestions.png  one row per registered edit (its round), under column titles: the suggestion, its guide,
                     the painted image, the mask, and the result (the avatar of the refine that first trained
                     on the edit, in the edit's pose)
    comparison.mp4   the held-out video under captions: ground truth | avatar 000 | the current avatar
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
from avatarperfect_cli.io import atomic_write_bytes, read_image
from avatarperfect_cli.io.outputs import check_output_folder
from avatarperfect_cli.io.video import frame_writer
from avatarperfect_cli.io.workspace import Workspace, open_workspace
from avatarperfect_cli.refinement.pictures import caption_strip, figure_png, labelled_grid
from avatarperfect_cli.stages.evaluate import evaluate
from avatarperfect_cli.stages.workspace_data import SUGGESTIONS, RegisteredEdit, registered_edits

WHITE = torch.ones(3)
MASK_TINT = torch.tensor([1.0, 0.0, 0.8])
REPORT_FILES = ("metrics.png", "suggestions.png", "comparison.mp4")
SHEET_COLUMNS = ["suggested", "guide: barely seen", "painted", "edit mask", "result after refine"]


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
    """PNG bytes: held-out PSNR, IoU and SSIM against the avatar iteration, one titled panel each."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    iterations = [r["iteration"] for r in results]
    figure, axes = plt.subplots(1, 3, figsize=(12, 3.6))
    panels = (("psnr", "PSNR (dB)", "tab:blue"), ("iou", "IoU", "tab:green"), ("ssim", "SSIM", "tab:purple"))
    for axis, (key, name, colour) in zip(axes, panels):
        axis.plot(iterations, [r["mean"][key] for r in results], "o-", color=colour)
        axis.set_title(f"held-out {name}, higher is better", fontsize=11)
        axis.set(xlabel="avatar iteration (0: before any edit)", ylabel=name)
        axis.set_xticks(iterations)
        axis.grid(alpha=0.3)
    return figure_png(figure, title)


def edits_sheet(workspace: Workspace, title: str) -> bytes | None:
    """PNG bytes: one row per registered edit, under SHEET_COLUMNS (the mask tinted over the suggestion; the
    result empty until a refine trained on the edit); None without edits."""
    import matplotlib

    matplotlib.use("Agg")
    rows, labels = [], []
    for round_number, edit in enumerate(registered_edits(workspace), start=1):
        record = json.loads((edit.folder / "edit.json").read_text())
        number = record["painted_over"].removeprefix("suggestion ")
        suggestion = workspace.root / SUGGESTIONS / number
        if not number.isdigit() or not suggestion.is_dir():
            continue
        suggested = read_image(suggestion / "suggested.png", "RGB")
        painted = read_image(next(edit.folder.glob("edited.*")), "RGB")
        mask = read_image(edit.folder / "mask.png", "L")
        masked = suggested * (1 - 0.6 * mask) + 0.6 * mask * MASK_TINT
        result = _first_result(workspace, edit)
        rows.append([suggested, read_image(suggestion / "guide.png", "RGB"), painted, masked, result])
        refined = "" if result is None else f", avatar {_first_refine(workspace, edit.number):03d}"
        labels.append(f"round {round_number}\nedit {edit.number:03d}{refined}")
    return figure_png(labelled_grid(rows, labels, SHEET_COLUMNS), title) if rows else None


def _first_refine(workspace: Workspace, number: int) -> int | None:
    """The avatar iteration of the first refine that trained on edit `number` (None: none yet)."""
    for entry in workspace.manifest.get("history", []):
        if entry.get("stage") == "refine" and number in entry.get("edits", []) and "avatar" in entry:
            return int(entry["avatar"])
    return None


def _first_result(workspace: Workspace, edit: RegisteredEdit) -> torch.Tensor | None:
    """(H, W, 3): the avatar of the first refine that trained on `edit`, in the edit's pose on white."""
    iteration = _first_refine(workspace, edit.number)
    if iteration is None or not workspace.avatar_path(iteration).is_file():
        return None
    avatar = Avatar.load(workspace.avatar_path(iteration))
    with torch.no_grad():
        return render_avatar(avatar, edit.pose.body_pose, edit.pose.transl, edit.pose.camera, WHITE).image.clamp(0, 1)


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
    sheet = edits_sheet(workspace, f"{workspace_root}: the edits, one round per row")
    test = load_people_snapshot(test_dataset, downscale=int(workspace.manifest.get("downscale", 1)))
    if not len(test):
        raise AvatarPerfectError(f"{test_dataset}: no frames")
    first, current = Avatar.load(workspace.require_avatar(0)), Avatar.load(workspace.require_avatar())
    height, width = test.images.shape[1:3]
    captions = caption_strip(["ground truth", "avatar 000", f"avatar {workspace.iteration:03d}"], width)
    with frame_writer(output_dir / "comparison.mp4", 3 * width, height + len(captions), fps) as write, torch.no_grad():
        for t in track(range(len(test)), description="comparison video", console=console, disable=not progress):
            views = [render_avatar(a, test.body_pose[t], test.transl[t], test.camera, WHITE).image for a in (first, current)]
            write(torch.cat([captions, torch.cat([test.images[t], *views], dim=1)], dim=0))
    atomic_write_bytes(output_dir / "metrics.png", metrics_plot(results, title))
    if sheet is not None:
        atomic_write_bytes(output_dir / "suggestions.png", sheet)
    console.print(f"wrote metrics.png, {'suggestions.png, ' if sheet is not None else ''}comparison.mp4 in {output_dir}")
    for result in results:
        mean = result["mean"]
        console.print(f"  avatar {result['iteration']:03d}: PSNR {mean['psnr']:.2f} dB, IoU {mean['iou']:.4f}, SSIM {mean['ssim']:.4f}")
    return output_dir
