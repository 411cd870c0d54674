"""The `relink` stage: point a workspace at its training video after the video moved.

The new folder must be the same video: the workspace's fingerprint (recorded by train-initial: frame count,
image size, SHA-256 of the camera and the images; `datasets.video_fingerprint`) must match. A workspace
without one is checked by image size (its camera at its downscale) and by the frames it trained on being
there, and gets the new folder's fingerprint. The manifest then names the folder relative to the workspace where possible, in one
commit with a history entry.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

from rich.console import Console

from avatarperfect_cli.datasets import VideoFingerprint, video_fingerprint
from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.io.workspace import MANIFEST, locked_workspace
from avatarperfect_cli.stages.workspace_data import load_video, training_camera


def relink(workspace_root: Path, dataset: Path, progress: bool = True) -> str:
    """Make the workspace's dataset `dataset` after checking it is the same video; returns what the manifest stores."""
    if not Path(dataset).is_dir():
        raise AvatarPerfectError(f"{dataset}: no such folder")
    with locked_workspace(workspace_root) as workspace:
        recorded = workspace.manifest.get("dataset_fingerprint")
        found = video_fingerprint(dataset, content=recorded is not None)
        if recorded is not None:
            try:
                expected = VideoFingerprint(**recorded)
            except TypeError:
                raise InputFileError(workspace.root / MANIFEST, f"'dataset_fingerprint' is malformed: {recorded!r:.80}") from None
            _compare(dataset, expected, found)
            checked = "frame count, image size and content"
        else:
            camera, downscale = training_camera(workspace), int(workspace.manifest.get("downscale", 1))
            if (found.width // downscale, found.height // downscale) != (camera.width, camera.height):
                raise AvatarPerfectError(
                    f"{dataset}: {found.width}x{found.height} images do not make the workspace's {camera.width}x{camera.height} "
                    f"at downscale {downscale}; not the same video"
                )
            found = video_fingerprint(dataset)
            checked = "image size and the frames the workspace trained on (it had no fingerprint)"
        workspace.set_dataset(dataset)
        reference = workspace.manifest["dataset"]
        load_video(workspace, with_images=False)  # its frames and pose file are there
        workspace.manifest["dataset_fingerprint"] = asdict(found)
        workspace.commit({"stage": "relink", "dataset": reference, "checked": checked})
    Console(stderr=True, quiet=not progress).print(
        f"{workspace_root} now reads its video from {dataset} (checked: {checked})", soft_wrap=True
    )
    return reference


def _compare(dataset: Path, expected: VideoFingerprint, found: VideoFingerprint) -> None:
    """One line naming the first difference between the workspace's video and `dataset`."""
    if expected.frames >= 0 and found.frames != expected.frames:
        raise AvatarPerfectError(f"{dataset}: {found.frames} frames, but the workspace's video has {expected.frames}; not the same video")
    if (found.width, found.height) != (expected.width, expected.height):
        raise AvatarPerfectError(
            f"{dataset}: {found.width}x{found.height} images, but the workspace's video has {expected.width}x{expected.height}; "
            "not the same video"
        )
    if expected.sha256 is not None and found.sha256 != expected.sha256:
        raise AvatarPerfectError(f"{dataset}: its camera or images differ from the workspace's video (content hash); not the same video")
