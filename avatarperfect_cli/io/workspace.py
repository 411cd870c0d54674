"""The workspace folder that every stage reads and writes, and its manifest `workspace.json`.

    ws/workspace.json        manifest: dataset, body model, camera, settings, iteration, history
    ws/avatar/000.ply        avatar after each iteration (000 = train-initial)
    ws/visibility/000.npy    accumulated per-Gaussian visibility
    ws/suggest/001/          suggested pose.json, render.png, guide.png
    ws/edits/001/            the user's edited.png and the derived mask.png
    ws/eval/000/test/        metrics.json and comparison image, per evaluated video

A new workspace is assembled in a hidden sibling folder and renamed into place, so an interrupted
train-initial leaves nothing behind; later stages write each file atomically.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.io.atomic import atomic_write_text, staging_dir

MANIFEST = "workspace.json"
WORKSPACE_FORMAT = "avatarperfect.workspace"
WORKSPACE_VERSION = 1


@dataclass
class Workspace:
    """A workspace folder and its manifest (a JSON-serialisable dict)."""

    root: Path
    manifest: dict[str, Any]

    @property
    def iteration(self) -> int:
        """The latest avatar iteration (0 after train-initial)."""
        return int(self.manifest["iteration"])

    def avatar_path(self, iteration: int | None = None) -> Path:
        return self.root / "avatar" / f"{self._iteration(iteration):03d}.ply"

    def eval_dir(self, iteration: int | None = None) -> Path:
        return self.root / "eval" / f"{self._iteration(iteration):03d}"

    def _iteration(self, iteration: int | None) -> int:
        return self.iteration if iteration is None else iteration

    def require_avatar(self, iteration: int | None = None) -> Path:
        """Path of an existing avatar PLY, or a one-line error naming the missing iteration."""
        path = self.avatar_path(iteration)
        if not path.is_file():
            raise AvatarPerfectError(f"{self.root}: no avatar for iteration {self._iteration(iteration)} ({path.name} is missing)")
        return path

    def save_manifest(self) -> None:
        atomic_write_text(self.root / MANIFEST, json.dumps(self.manifest, indent=2) + "\n")


def open_workspace(root: Path) -> Workspace:
    """Read an existing workspace; a one-line error if `root` is not one."""
    path = root / MANIFEST
    if not path.is_file():
        raise AvatarPerfectError(f"{root}: not a workspace (no {MANIFEST}); run 'avatarperfect train-initial' first")
    try:
        manifest = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise InputFileError(path, f"unreadable manifest ({error})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != WORKSPACE_FORMAT:
        raise InputFileError(path, f"not an avatarperfect manifest (format must be '{WORKSPACE_FORMAT}')")
    if manifest.get("version", 0) > WORKSPACE_VERSION:
        raise InputFileError(path, f"manifest version {manifest['version']} is newer than this avatarperfect reads")
    if not isinstance(manifest.get("iteration"), int):
        raise InputFileError(path, "manifest has no integer 'iteration'")
    return Workspace(root, manifest)


def check_new_workspace(root: Path, force: bool) -> None:
    """Refuse to overwrite an existing folder unless `force` (and never a non-workspace folder)."""
    if not root.exists():
        return
    if not (root / MANIFEST).is_file() and any(root.iterdir()):
        raise AvatarPerfectError(f"{root}: exists and is not a workspace; choose another folder")
    if (root / MANIFEST).is_file() and not force:
        raise AvatarPerfectError(f"{root}: workspace exists; pass --force to replace it")


@contextmanager
def new_workspace(root: Path, manifest: dict[str, Any], force: bool = False) -> Iterator[Workspace]:
    """Build a workspace in a hidden sibling folder; on success it replaces `root` in one rename.

    The manifest gets the format and version keys; the caller fills the folder through the yielded
    Workspace (whose root is the staging folder) and must not keep it after the block.
    """
    check_new_workspace(root, force)
    staging = staging_dir(root)
    try:
        workspace = Workspace(staging, {"format": WORKSPACE_FORMAT, "version": WORKSPACE_VERSION, **manifest})
        yield workspace
        workspace.save_manifest()
        if root.exists():
            retired = staging.with_name(staging.name + "-old")
            os.replace(root, retired)
            os.replace(staging, root)
            shutil.rmtree(retired, ignore_errors=True)
        else:
            os.replace(staging, root)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
