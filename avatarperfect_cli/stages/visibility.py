"""The `visibility` stage: accumulated per-Gaussian visibility V of the current avatar iteration.

Writes ws/visibility/NNN.npz (NNN = avatar iteration) holding
    visibility  (N,) float64 V, pixels per view
    video       (N,) float64 the video term alone (the mean over the frames): when only the registered
                edits changed, V is brought up to date by rendering the edit views alone
    mean        V's mean
    frames      video frames accumulated;  edits: the edit folders accumulated (names)
    edit_weight w;  iteration: the avatar iteration;  gaussians: N
and ws/visibility/NNN.png, the avatar in revealing poses coloured by V, with the body regions' shares of
barely seen Gaussians (also printed).
"""

from __future__ import annotations

import io
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from rich.console import Console
from rich.progress import track

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.devices import CPU
from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.io import atomic_write_bytes
from avatarperfect_cli.io.atomic import updated_folder
from avatarperfect_cli.io.workspace import Workspace, locked_workspace
from avatarperfect_cli.refinement.pictures import visibility_picture
from avatarperfect_cli.refinement.visibility import BARELY_SEEN, DEFAULT_EDIT_WEIGHT, combine_visibility, gaussian_visibility
from avatarperfect_cli.refinement.where_to_look import barely_seen_by_region, revealing_exposure
from avatarperfect_cli.stages.workspace_data import registered_edits, video_poses

VISIBILITY = "visibility"


@dataclass
class VisibilityRecord:
    """The content of ws/visibility/NNN.npz (see the module doc); `visibility` and `video` (N,) float64 on
    the CPU (`video` None in files written before it was stored)."""

    visibility: torch.Tensor
    video: torch.Tensor | None
    frames: int
    edits: list[str]
    edit_weight: float
    iteration: int

    def matches(self, iteration: int, edits: list[str], edit_weight: float, gaussians: int) -> bool:
        return (self.iteration, self.edits, self.edit_weight, len(self.visibility)) == (iteration, edits, edit_weight, gaussians)


def visibility_path(workspace: Workspace, iteration: int | None = None) -> Path:
    return workspace.root / VISIBILITY / f"{workspace.iteration if iteration is None else iteration:03d}.npz"


def read_visibility(path: Path, iteration: int) -> VisibilityRecord:
    """Read a visibility file; one line when it is unreadable or belongs to another avatar iteration."""
    try:
        with np.load(path) as data:
            video = torch.from_numpy(data["video"].astype(np.float64)) if "video" in data else None
            record = VisibilityRecord(
                torch.from_numpy(data["visibility"].astype(np.float64)), video, int(data["frames"]),
                [str(name) for name in data["edits"]], float(data["edit_weight"]), int(data["iteration"]),
            )  # fmt: skip
    except (OSError, KeyError, ValueError, TypeError) as error:
        raise InputFileError(path, f"not a visibility file ({error}); delete it and run 'avatarperfect visibility'") from None
    if record.iteration != iteration:
        raise InputFileError(path, f"belongs to avatar iteration {record.iteration}, not {iteration}; delete it")
    for values in (record.visibility, record.video):
        if values is not None and (values.shape != record.visibility.shape or values.ndim != 1 or not torch.isfinite(values).all()):
            raise InputFileError(path, "visibility is not a finite (N,) array; delete it")
    return record


def compute_visibility(
    workspace: Workspace, avatar: Avatar, edit_weight: float, progress: bool, video: torch.Tensor | None = None
) -> VisibilityRecord:
    """V of `avatar` over the workspace's video and registered edits, rendered on the avatar's device;
    writes the .npz and the picture. video: the (N,) video term of this avatar when already known (then
    only the edit views are rendered)."""
    if not 0.0 <= edit_weight <= 1.0:
        raise AvatarPerfectError(f"--edit-weight must be in [0, 1], got {edit_weight}")
    views = video_poses(workspace)
    edits = registered_edits(workspace)
    console = Console(stderr=True, quiet=not progress)
    start = time.perf_counter()
    if video is None:
        total = torch.zeros(len(avatar), dtype=torch.float64, device=avatar.device)
        for view in track(views, description="visibility", console=console, disable=not progress):
            total += gaussian_visibility(avatar, view)
        video = (total / len(views)).cpu()
    edit_mean = None
    if edits:
        edit_mean = (sum(gaussian_visibility(avatar, edit.pose) for edit in edits) / len(edits)).cpu()
    visibility = combine_visibility(video, edit_mean, edit_weight)
    record = VisibilityRecord(visibility, video, len(views), [edit.folder.name for edit in edits], edit_weight, workspace.iteration)
    path = visibility_path(workspace)
    buffer = io.BytesIO()
    np.savez(
        buffer, visibility=visibility.numpy(), video=video.numpy(), mean=float(visibility.mean()), frames=len(views),
        edits=np.array(record.edits, dtype=str),
        edit_weight=edit_weight, iteration=workspace.iteration, gaussians=len(avatar),
    )  # fmt: skip
    title = f"avatar {workspace.iteration:03d}: visibility over {len(views)} frames and {len(edits)} edits"
    exposure = revealing_exposure(avatar)
    shares = barely_seen_by_region(avatar, visibility, exposure)
    picture = visibility_picture(avatar, visibility, exposure, shares, title)
    with updated_folder(path.parent) as staging:  # the record and its picture appear together
        atomic_write_bytes(staging / path.name, buffer.getvalue())
        atomic_write_bytes(staging / path.with_suffix(".png").name, picture)
    console.print(f"wrote {path} and {path.with_suffix('.png').name} ({time.perf_counter() - start:.1f} s)")
    console.print(
        f"barely seen (V below {BARELY_SEEN:.0%} of its mean) by body region, of what revealing poses show; check the first first: "
        + ", ".join(f"{name} {share:.0%}" for name, share, _ in shares)
    )
    return record


def current_visibility(workspace: Workspace, avatar: Avatar, edit_weight: float, progress: bool) -> VisibilityRecord:
    """The stored V of the current iteration if it is up to date (same edits and weight), else computed anew
    (only the edit term when the stored record holds the video term of the same frames)."""
    path = visibility_path(workspace)
    if path.is_file():
        record = read_visibility(path, workspace.iteration)
        edits = [edit.folder.name for edit in registered_edits(workspace)]
        if record.matches(workspace.iteration, edits, edit_weight, len(avatar)):
            return record
        if len(record.visibility) != len(avatar):
            raise InputFileError(path, f"holds {len(record.visibility)} values for {len(avatar)} Gaussians; delete it")
        if record.video is not None and record.frames == len(video_poses(workspace)):
            return compute_visibility(workspace, avatar, edit_weight, progress, video=record.video)
    return compute_visibility(workspace, avatar, edit_weight, progress)


def visibility(
    workspace_root: Path, edit_weight: float = DEFAULT_EDIT_WEIGHT, progress: bool = True, device: torch.device = CPU
) -> Path:
    """Compute V for the workspace's current avatar, rendering on `device`, and write ws/visibility/NNN.npz
    (+ .png); returns its path."""
    with locked_workspace(workspace_root) as workspace:
        avatar = Avatar.load(workspace.require_avatar()).to(device)
        compute_visibility(workspace, avatar, edit_weight, progress)
        return visibility_path(workspace)
