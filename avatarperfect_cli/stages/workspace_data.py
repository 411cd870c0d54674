"""What the refinement stages read from a workspace: its video (with refined poses), its training
camera and reference pose, and its registered edits.

    ws/edits/NNN/edited.png      the painted image as the user gave it
    ws/edits/NNN/target.png      the colours to learn (white where background)
    ws/edits/NNN/mask.png        M_k, the supervised pixels (white = in)
    ws/edits/NNN/background.png  the pixels painted as background (white = in)
    ws/edits/NNN/pose.json       the body pose and camera the edit was painted in
    ws/edits/NNN/edit.json       provenance: source file, suggestion, time, pixel counts; the edit's strength
                                 and the error of the image painted over inside M_k (refinement/edit_progress.py)
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from avatarperfect_cli.body import BodyTemplate, load_described_template
from avatarperfect_cli.datasets import FrameRange, VideoDataset, load_people_snapshot
from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.io import PoseFile, read_image, read_pose
from avatarperfect_cli.io.camera_json import camera_from_json
from avatarperfect_cli.io.workspace import MANIFEST, Workspace
from avatarperfect_cli.refinement.additional_training import EDIT_STRENGTHS
from avatarperfect_cli.render import Camera
from avatarperfect_cli.training.trainer import TrainingView

EDITS = "edits"
# what numpy raises on a missing, truncated or foreign .npz
UNREADABLE_NPZ = (OSError, EOFError, zipfile.BadZipFile, KeyError, TypeError, ValueError)
SUGGESTIONS = "suggestions"


def training_camera(workspace: Workspace) -> Camera:
    """The camera of the workspace's video at its training resolution."""
    camera = workspace.manifest.get("camera")
    if not isinstance(camera, dict):
        raise InputFileError(workspace.root / MANIFEST, "manifest has no 'camera' object")
    return camera_from_json(camera, workspace.root / MANIFEST, where="camera.")


def reference_pose(workspace: Workspace) -> PoseFile:
    """The pose the avatar was trained in (the video's first frame) seen by the training camera."""
    reference = workspace.manifest.get("reference_pose")
    try:
        body_pose = torch.tensor(reference["body_pose"], dtype=torch.float32)
        transl = torch.tensor(reference["transl"], dtype=torch.float32)
        return PoseFile(body_pose, transl, training_camera(workspace))
    except (TypeError, KeyError, ValueError):
        raise InputFileError(workspace.root / MANIFEST, "manifest 'reference_pose' is missing or malformed") from None


def transl_offset(workspace: Workspace) -> torch.Tensor:
    """(3,) metres: what train-initial added to the dataset's translations so the template lands on the
    subject (manifest "transl_offset"; zeros for workspaces from before it was recorded)."""
    offset = workspace.manifest.get("transl_offset", [0.0, 0.0, 0.0])
    try:
        values = torch.tensor(offset, dtype=torch.float32)
    except (TypeError, ValueError):
        values = torch.empty(0)
    if values.shape != (3,) or not values.isfinite().all():
        raise InputFileError(workspace.root / MANIFEST, f"'transl_offset' must be 3 finite numbers (metres), got {offset!r}")
    return values


def load_video(workspace: Workspace, with_images: bool = True) -> VideoDataset:
    """The workspace's training video at its training resolution, from the pose file it trained on, its
    translations moved by the workspace's offset, with the refined poses where `train-initial
    --refine-poses` saved them; one line naming the manifest if the dataset moved."""
    manifest = workspace.manifest
    dataset = workspace.dataset()
    if not dataset.is_dir():
        raise InputFileError(
            workspace.root / MANIFEST,
            f"its dataset {dataset} is missing (moved or deleted?); point the workspace at it with "
            f"'avatarperfect relink {workspace.root} DATASET'",
        )
    frames = manifest.get("frames")
    frame_range = None if frames is None else FrameRange(**frames)
    poses = manifest.get("poses")  # absent in workspaces from before it was recorded: the loader's old choice
    if poses is not None and not isinstance(poses, str):
        raise InputFileError(workspace.root / MANIFEST, f"'poses' must name the pose file, got {poses!r}")
    video = load_people_snapshot(
        dataset, frame_range, downscale=int(manifest.get("downscale", 1)), pose_source=poses or "auto", with_images=with_images
    )
    video.transl = video.transl + transl_offset(workspace)
    refined = manifest.get("refined_poses")
    if refined:
        path = workspace.root / refined
        try:
            with np.load(path) as data:
                frame_ids, body_pose, transl = data["frame_ids"], data["body_pose"], data["transl"]
        except UNREADABLE_NPZ as error:
            raise InputFileError(path, f"unreadable refined poses ({error})") from None
        if not np.array_equal(frame_ids, video.frame_ids.numpy()):
            raise InputFileError(path, "refined poses do not cover the workspace's frames")
        video.body_pose, video.transl = torch.from_numpy(body_pose).float(), torch.from_numpy(transl).float()
    return video


def body_template(workspace: Workspace, body_model: dict, smpl_model_dir: Path | None = None) -> BodyTemplate:
    """The body the workspace's avatars were built on: the template train-initial saved (manifest
    "body_template"), else the one the avatar's `body_model` metadata describes (rebuilt from the body model;
    SMPL needs `smpl_model_dir`)."""
    saved = workspace.manifest.get("body_template")
    if not saved:
        return load_described_template(body_model, smpl_model_dir)
    path = workspace.root / str(saved)
    try:
        return BodyTemplate.load(path)
    except UNREADABLE_NPZ as error:
        raise InputFileError(path, f"unreadable body template ({error})") from None


def video_poses(workspace: Workspace) -> list[PoseFile]:
    """One pose file per training frame (refined poses where available), training camera."""
    video = load_video(workspace, with_images=False)
    return [PoseFile(video.body_pose[t], video.transl[t], video.camera) for t in range(len(video))]


@dataclass
class RegisteredEdit:
    """An edit under ws/edits/NNN: folder, pose and, once loaded, what refine trains on."""

    folder: Path
    pose: PoseFile

    @property
    def number(self) -> int:
        return int(self.folder.name)

    def training_view(self) -> TrainingView:
        """The edit as a masked training view: target colours inside M_k; background pixels have no
        foreground, so their target is the step's random background (alpha must go to 0)."""
        target = read_image(self.folder / "target.png", "RGB")
        mask = read_image(self.folder / "mask.png", "L")[..., 0] >= 0.5
        background = read_image(self.folder / "background.png", "L")[..., 0] >= 0.5
        return TrainingView(target, mask & ~background, self.pose.body_pose, self.pose.transl, self.pose.camera, mask)

    def background(self) -> torch.Tensor:
        return read_image(self.folder / "background.png", "L")[..., 0] >= 0.5

    def record(self) -> dict:
        """edit.json's content; one line naming the file when it is not a JSON object."""
        path = self.folder / "edit.json"
        try:
            record = json.loads(path.read_text())
        except (OSError, ValueError) as error:
            raise InputFileError(path, f"not readable JSON ({error})") from None
        if not isinstance(record, dict):
            raise InputFileError(path, "not a JSON object")
        return record

    @property
    def painted_over_error(self) -> float | None:
        """The squared error of the image painted over inside M_k (None for edits registered before it was
        recorded)."""
        error = self.record().get("painted_over_error")
        if error is not None and (not isinstance(error, (int, float)) or not 0.0 <= error < float("inf")):
            raise InputFileError(self.folder / "edit.json", f"'painted_over_error' must be a number >= 0, got {error!r}")
        return error

    @property
    def strength(self) -> str:
        """How refine weighs the edit against the video ("default" for edits registered without one)."""
        strength = self.record().get("strength", "default")
        if strength not in EDIT_STRENGTHS:
            raise InputFileError(self.folder / "edit.json", f"unknown strength {strength!r}; use one of {', '.join(EDIT_STRENGTHS)}")
        return strength


def registered_edits(workspace: Workspace) -> list[RegisteredEdit]:
    """The complete edits under ws/edits, in order."""
    edits = []
    for folder in workspace.numbered_folders(EDITS):
        if not (folder / "edit.json").is_file():
            raise InputFileError(folder, "incomplete edit (no edit.json); remove it with 'apply-edit --remove'")
        edits.append(RegisteredEdit(folder, read_pose(folder / "pose.json")))
    return edits


def latest_suggestion(workspace: Workspace) -> Path:
    """The newest ws/suggestions/NNN folder; a one-line error when there is none."""
    folders = workspace.numbered_folders(SUGGESTIONS)
    if not folders:
        raise AvatarPerfectError(f"{workspace.root}: no suggestion yet; run 'avatarperfect suggest {workspace.root}' first")
    return folders[-1]


def applied_edits(workspace: Workspace) -> list[int]:
    """The edits whose background deletions the current avatar iteration already carries (from the
    history entry that wrote it)."""
    for entry in reversed(workspace.manifest.get("history", [])):
        if entry.get("avatar") == workspace.iteration:
            return list(entry.get("applied_edits", []))
    return []
