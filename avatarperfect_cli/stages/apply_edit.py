"""The `apply-edit` stage: register a painted image as an edit, list or withdraw edits, fill a selected
region with a built-in tool, or erase Gaussians as SuperSplat does (the study's baselines).

An edit is painted over the latest suggestion (its suggested.png and pose.json) or over the avatar
rendered in a pose JSON given with --pose. It is registered as ws/edits/NNN/ in one step (see
`stages.workspace_data` for the files); `refine` then trains on it.
"""

from __future__ import annotations

import datetime
import json
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from rich.console import Console
from rich.table import Table

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.io import PoseFile, atomic_write_text, read_image, read_pose, write_image, write_pose
from avatarperfect_cli.io.images import image_size
from avatarperfect_cli.io.atomic import atomic_folder
from avatarperfect_cli.io.workspace import Workspace, locked_workspace, reading_workspace
from avatarperfect_cli.refinement.additional_training import EDIT_STRENGTHS
from avatarperfect_cli.refinement.edit_image import EditMasks, derive_edit_masks, read_painted_image, read_user_mask
from avatarperfect_cli.refinement.edit_progress import paint_error
from avatarperfect_cli.refinement.erase import ERASE_MODES, delete_gaussians, select_in_region
from avatarperfect_cli.refinement.inpaint import OPENCV_METHODS, fill_diffusion, fill_flat, fill_opencv, parse_colour
from avatarperfect_cli.stages.workspace_data import EDITS, applied_edits, latest_suggestion, registered_edits

WHITE = torch.ones(3)


class UnchangedImage(AvatarPerfectError):
    """The painted image equals what it was painted over: there is no edit to register."""


@dataclass
class EditSource:
    """What the user painted over: the image (H, W, 3) in [0, 1], its pose, and where they came from."""

    image: torch.Tensor
    pose: PoseFile
    origin: str


def edit_source(workspace: Workspace, pose_path: Path | None) -> EditSource:
    """The latest suggestion, or the current avatar rendered in `pose_path`'s pose and camera."""
    if pose_path is not None:
        pose = read_pose(pose_path)
        avatar = Avatar.load(workspace.require_avatar())
        with torch.no_grad():
            image = render_avatar(avatar, pose.body_pose, pose.transl, pose.camera, WHITE).image.clamp(0, 1)
        # the user painted over a PNG: compare with the same 8-bit values
        return EditSource(torch.round(image * 255) / 255, pose, str(Path(pose_path).resolve()))
    folder = latest_suggestion(workspace)
    return EditSource(read_image(folder / "suggested.png", "RGB"), read_pose(folder / "pose.json"), f"suggestion {folder.name}")


def check_strength(strength: str) -> None:
    if strength not in EDIT_STRENGTHS:
        raise AvatarPerfectError(f"--strength must be one of {', '.join(EDIT_STRENGTHS)}, got {strength!r}")


def register_edit(workspace: Workspace, edited: Path, source: EditSource, masks: EditMasks, strength: str = "default") -> Path:
    """Write ws/edits/NNN/ atomically; returns the folder."""
    folder = workspace.next_numbered_folder(EDITS)
    counts = masks.counts()
    with atomic_folder(folder) as staging:
        shutil.copyfile(edited, staging / f"edited{edited.suffix.lower()}")
        write_image(staging / "target.png", masks.target)
        write_image(staging / "mask.png", masks.edit.float()[..., None])
        write_image(staging / "background.png", masks.background.float()[..., None])
        write_pose(staging / "pose.json", source.pose)
        record = {
            "source_file": str(Path(edited).resolve()),
            "painted_over": source.origin,
            "avatar_iteration": workspace.iteration,
            "time": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "pixels": counts,
            "strength": strength,
            # refine reports how far it went from here toward the paint (refinement/edit_progress.py)
            "painted_over_error": paint_error(source.image, masks.target, masks.edit),
        }
        atomic_write_text(staging / "edit.json", json.dumps(record, indent=2) + "\n")
    return folder


def apply_edit(
    workspace_root: Path, edited: Path, pose: Path | None = None, mask: Path | None = None, progress: bool = True,
    hint: bool = True, strength: str = "default",
) -> Path:  # fmt: skip
    """Register the painted image `edited` (see the module doc); returns the edit's folder. hint: print the
    command to run next; strength: how refine weighs the edit against the video (`EDIT_STRENGTHS`)."""
    check_strength(strength)
    console = Console(stderr=True, quiet=not progress)
    with locked_workspace(workspace_root) as workspace:
        source = edit_source(workspace, pose)
        height, width = source.image.shape[:2]
        painted_width, painted_height = image_size(edited)  # from the header: a wrong size is not decoded
        if (painted_height, painted_width) != (height, width):
            raise AvatarPerfectError(
                f"{edited}: the image is {painted_width}x{painted_height} pixels but {source.origin} is "
                f"{width}x{height}; paint on the suggested image at its own size"
            )
        painted = read_painted_image(edited)
        if painted.lossy:
            console.print(f"[yellow]warning[/]: {edited} is lossy (JPEG); compression noise is ignored, but save PNGs")
        user_mask = None if mask is None else read_user_mask(mask, (height, width))
        masks = derive_edit_masks(painted, source.image, user_mask=user_mask)
        if not masks.edit.any():
            raise UnchangedImage(f"{edited}: no pixel differs from {source.origin}; nothing to register")
        folder = register_edit(workspace, Path(edited), source, masks, strength)
    counts = masks.counts()
    console.print(
        f"registered edit {folder.name} over {source.origin}: {counts['edited']:,} pixels "
        f"({counts['background']:,} background, {counts['colour']:,} colour)" + ("" if strength == "default" else f", {strength}")
    )
    if hint:
        console.print(f"next: avatarperfect refine {workspace_root}", highlight=False)
    return folder


def list_edits(workspace_root: Path) -> list[dict]:
    """The registered edits' records (printed as a table); read-only: no lock needed (see `reading_workspace`)."""
    with reading_workspace(workspace_root) as workspace:
        edits = registered_edits(workspace)
        applied = set()
        for entry in workspace.manifest.get("history", []):
            applied |= set(entry.get("edits", []))
        records = [json.loads((edit.folder / "edit.json").read_text()) | {"number": edit.number} for edit in edits]
    table = Table(title=f"{len(records)} edits in {workspace_root}")
    for column in ("edit", "painted over", "pixels", "background", "strength", "registered", "refined"):
        table.add_column(column)
    for record in records:
        pixels = record["pixels"]
        table.add_row(
            f"{record['number']:03d}", record["painted_over"], f"{pixels['edited']:,}", f"{pixels['background']:,}",
            record.get("strength", "default"), record["time"], "yes" if record["number"] in applied else "not yet",
        )  # fmt: skip
    Console().print(table)
    return records


def set_edit_strength(workspace_root: Path, number: int, strength: str) -> None:
    """Change edit `number`'s strength (its edit.json, rewritten atomically); the next refine trains it so."""
    check_strength(strength)
    with locked_workspace(workspace_root) as workspace:
        path = workspace.root / EDITS / f"{number:03d}" / "edit.json"
        if not path.is_file():
            raise AvatarPerfectError(f"{workspace_root}: no edit {number} (see 'apply-edit --list')")
        record = json.loads(path.read_text()) | {"strength": strength}
        atomic_write_text(path, json.dumps(record, indent=2) + "\n")


def remove_edit(workspace_root: Path, number: int) -> None:
    """Withdraw edit `number`: its folder goes in one rename; refines after this no longer use it."""
    with locked_workspace(workspace_root) as workspace:
        folder = workspace.root / EDITS / f"{number:03d}"
        if not folder.is_dir():
            raise AvatarPerfectError(f"{workspace_root}: no edit {number} (see 'apply-edit --list')")
        withdrawn = folder.with_name(f".{folder.name}.withdrawn.tmp")
        folder.rename(withdrawn)
        shutil.rmtree(withdrawn)


def erase_region(workspace_root: Path, region_path: Path, mode: str, pose: Path | None = None, progress: bool = True) -> Path:
    """SuperSplat's erase tools: delete the Gaussians selected by `region_path` (a mask PNG over the latest
    suggestion or `pose`'s view) with `mode` "center" or "splat", and write the next avatar iteration
    without training. Returns its path."""
    if mode not in ERASE_MODES:
        raise AvatarPerfectError(f"--erase {mode}: give {' or '.join(ERASE_MODES)}")
    console = Console(stderr=True, quiet=not progress)
    with locked_workspace(workspace_root) as workspace:
        start = time.perf_counter()
        source = edit_source(workspace, pose)
        region = read_user_mask(region_path, tuple(source.image.shape[:2]))
        if not region.any():
            raise AvatarPerfectError(f"{region_path}: the region is empty")
        avatar = Avatar.load(workspace.require_avatar())
        selected = select_in_region(avatar, source.pose, region, mode)
        avatar = delete_gaussians(avatar, selected)
        iteration = max(workspace.committed_avatars()) + 1
        path = workspace.avatar_path(iteration)
        avatar.save(path)
        entry = {
            "stage": f"erase-{mode}", "avatar": iteration, "from": workspace.iteration, "painted_over": source.origin,
            "applied_edits": applied_edits(workspace),
            "deleted": int(selected.sum()), "seconds": round(time.perf_counter() - start, 1), "gaussians": len(avatar),
        }  # fmt: skip
        workspace.commit(entry, iteration)
    console.print(f"erase-{mode}: deleted {int(selected.sum()):,} Gaussians; wrote {path}")
    return path


def fill_region(
    workspace_root: Path, region_path: Path, fill: str, pose: Path | None = None, model_dir: Path | None = None,
    prompt: str = "", progress: bool = True,
) -> list[Path]:  # fmt: skip
    """The built-in fill tools over the latest suggestion (or `pose`'s view), inside the selection mask
    `region_path`: a flat colour, OpenCV inpainting ("telea", "ns") or diffusion inpainting ("diffusion",
    from the local pipeline in `model_dir`). A colour or OpenCV fill is registered as an edit at once
    (its mask is the region); diffusion writes 3 candidates beside the suggestion for the user to pick
    one and register with `apply-edit WS CANDIDATE.png --mask REGION.png`. Returns the written paths."""
    console = Console(stderr=True, quiet=not progress)
    with locked_workspace(workspace_root) as workspace:
        source = edit_source(workspace, pose)
        region = read_user_mask(region_path, tuple(source.image.shape[:2]))
        if not region.any():
            raise AvatarPerfectError(f"{region_path}: the region is empty")
        if fill == "diffusion":
            if model_dir is None:
                raise AvatarPerfectError("--fill diffusion needs --model-dir, your local Stable-Diffusion inpainting pipeline")
            folder = latest_suggestion(workspace) if pose is None else Path(pose).parent
            candidates = fill_diffusion(source.image, region, model_dir, prompt)
            paths = [folder / f"candidate_{index}.png" for index in range(1, len(candidates) + 1)]
            for path, candidate in zip(paths, candidates):
                write_image(path, candidate)
            console.print(f"wrote {len(paths)} candidates in {folder}; register the one you like with")
            console.print(f"  avatarperfect apply-edit {workspace_root} {paths[0]} --mask {region_path}", highlight=False)
            return paths
        if fill in OPENCV_METHODS:
            filled = fill_opencv(source.image, region, fill)
        else:
            filled = fill_flat(source.image, region, parse_colour(fill))
        filled_path = workspace.root / EDITS / f".fill-{fill.strip('#')}.tmp-edit.png"  # a kill leaves a temporary
        write_image(filled_path, filled)
        try:
            painted = read_painted_image(filled_path)
            masks = derive_edit_masks(painted, source.image, user_mask=region)
            folder = register_edit(workspace, filled_path, source, masks)
        finally:
            filled_path.unlink(missing_ok=True)
    console.print(f"registered edit {folder.name}: {fill} fill of {int(region.sum()):,} pixels over {source.origin}")
    return [folder]
