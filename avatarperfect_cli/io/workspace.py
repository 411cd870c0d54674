"""The workspace folder that every stage reads and writes, and its manifest `workspace.json`.

    ws/workspace.json        manifest: dataset (relative to the workspace where possible) and its fingerprint,
                             body model, camera, settings, iteration, history
    ws/avatar/000.ply        avatar after each iteration (000 = train-initial)
    ws/visibility/000.npy    accumulated per-Gaussian visibility
    ws/suggest/001/          suggested pose.json, render.png, guide.png
    ws/edits/001/            the user's edited.png and the derived mask.png
    ws/eval/000/test/        metrics.json and comparison image, per evaluated video

A new workspace is assembled in a hidden sibling folder and renamed into place, so an interrupted
train-initial leaves nothing behind; later stages write each file or folder atomically and commit by
rewriting the manifest last. Every stage that writes a workspace holds its lock (`locked_workspace`),
and the next stage to take the lock removes what a killed one left behind.
"""

from __future__ import annotations

import fcntl
import json
import os
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from avatarperfect_cli import interrupts
from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.io.atomic import atomic_folder, atomic_write_text, recover_folder, remove_temporaries

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

    def commit(self, entry: dict[str, Any], iteration: int | None = None) -> None:
        """Append `entry` to the history (and make `iteration` current) in one atomic manifest write:
        the step that makes a stage's already written files part of the workspace. An entry that
        wrote an avatar names its iteration under "avatar"."""
        self.manifest.setdefault("history", []).append(entry)
        if iteration is not None:
            self.manifest["iteration"] = iteration
        self.save_manifest()

    def committed_avatars(self) -> set[int]:
        """Iterations whose avatar the history records (iteration 0 always: train-initial)."""
        history = self.manifest.get("history", [])
        return {0} | {entry["avatar"] for entry in history if isinstance(entry.get("avatar"), int)}

    def numbered_folders(self, kind: str) -> list[Path]:
        """The complete folders ws/KIND/NNN (suggestions, edits), in numerical order."""
        parent = self.root / kind
        if not parent.is_dir():
            return []
        return sorted((p for p in parent.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name))

    def next_numbered_folder(self, kind: str) -> Path:
        """ws/KIND/NNN for the next free number, counting from 1 (numbers are never reused)."""
        existing = [int(p.name) for p in self.numbered_folders(kind)]
        return self.root / kind / f"{max(existing, default=0) + 1:03d}"

    def dataset(self) -> Path:
        """The training video's folder: the manifest's "dataset" (relative to the workspace unless absolute), or
        where it is missing, "dataset_absolute" when that folder is there (a workspace copied without its video)."""
        relative = self.root / str(self.manifest.get("dataset", ""))
        absolute = Path(str(self.manifest.get("dataset_absolute", "")))
        return absolute if not relative.is_dir() and absolute.is_absolute() and absolute.is_dir() else relative

    def set_dataset(self, dataset: Path) -> None:
        """Record `dataset` in the manifest (to be committed): relative to the workspace where there is such a path
        (another drive has none), and absolute."""
        absolute = os.path.abspath(dataset)
        try:
            self.manifest["dataset"] = os.path.relpath(absolute, os.path.abspath(self.root))
        except ValueError:
            self.manifest["dataset"] = absolute
        self.manifest["dataset_absolute"] = absolute

    def remove_uncommitted(self) -> None:
        """Delete avatar files a killed stage wrote but never committed to the manifest."""
        committed = self.committed_avatars()
        for path in (self.root / "avatar").glob("*.ply"):
            if path.stem.isdigit() and int(path.stem) not in committed:
                path.unlink(missing_ok=True)


def open_workspace(root: Path) -> Workspace:
    """Read an existing workspace; a one-line error if `root` is not one or its manifest fails `check_manifest`."""
    path = root / MANIFEST
    if not path.is_file():
        raise AvatarPerfectError(f"{root}: not a workspace (no {MANIFEST}); run 'avatarperfect train-initial' first")
    try:
        manifest = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise InputFileError(path, f"unreadable manifest ({error})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != WORKSPACE_FORMAT:
        raise InputFileError(path, f"not an avatarperfect manifest (format must be '{WORKSPACE_FORMAT}')")
    if _is_count(manifest.get("version", 0)) and manifest.get("version", 0) > WORKSPACE_VERSION:
        raise InputFileError(path, f"manifest version {manifest['version']} is newer than this avatarperfect reads")
    if not isinstance(manifest.get("iteration"), int):
        raise InputFileError(path, "manifest has no integer 'iteration'")
    check_manifest(manifest, path)
    return Workspace(root, manifest)


# The manifest's keys and history entries' keys -> (the JSON types allowed, how the error names them). Keys may be
# missing (older workspaces); the stages that need one say so. Deeper values (camera, pose) are checked where read.
_OBJECT, _TEXT, _COUNT = ((dict,), "an object"), ((str,), "a string"), (("count",), "a non-negative integer")
_MANIFEST_TYPES: dict[str, tuple[tuple, str]] = {
    "version": _COUNT, "iteration": _COUNT, "dataset": _TEXT, "frames": ((dict, None), "an object or null"),
    "poses": ((str, None), "a string or null"), "transl_offset": (("numbers",), "a list of numbers"),
    "downscale": _COUNT, "camera": _OBJECT, "body_model": _OBJECT, "reference_pose": _OBJECT,
    "refined_poses": ((str, None), "a string or null"), "body_template": ((str, None), "a string or null"), "history": ((list,), "a list of objects"),
    "dataset_fingerprint": _OBJECT, "dataset_absolute": _TEXT,
}  # fmt: skip
_HISTORY_TYPES: dict[str, tuple[tuple, str]] = {
    "stage": _TEXT, "avatar": _COUNT, "from": _COUNT, "edits": (("counts",), "a list of non-negative integers"),
    "applied_edits": (("counts",), "a list of non-negative integers"),
}  # fmt: skip


def check_manifest(manifest: dict[str, Any], path: Path) -> None:
    """Raise InputFileError naming the manifest and the field whose value has the wrong type."""
    for key, expected in _MANIFEST_TYPES.items():
        if key in manifest:
            _check_type(manifest[key], expected, key, path)
    for index, entry in enumerate(manifest.get("history", [])):
        if not isinstance(entry, dict):
            raise InputFileError(path, f"'history[{index}]' must be an object, got {entry!r:.40}")
        for key, expected in _HISTORY_TYPES.items():
            if key in entry:
                _check_type(entry[key], expected, f"history[{index}].{key}", path)


def _check_type(value: Any, expected: tuple[tuple, str], field: str, path: Path) -> None:
    kinds, description = expected
    if not any(_is_kind(value, kind) for kind in kinds):
        raise InputFileError(path, f"'{field}' must be {description}, got {value!r:.40}")


def _is_kind(value: Any, kind: Any) -> bool:
    if kind is None:
        return value is None
    if kind == "count":
        return _is_count(value)
    if kind == "counts":
        return isinstance(value, list) and all(_is_count(item) for item in value)
    if kind == "numbers":
        return isinstance(value, list) and all(isinstance(item, (int, float)) and not isinstance(item, bool) for item in value)
    return isinstance(value, kind) and not isinstance(value, bool)


def _is_count(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


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
    with atomic_folder(root) as staging:
        workspace = Workspace(staging, {"format": WORKSPACE_FORMAT, "version": WORKSPACE_VERSION, **manifest})
        yield workspace
        workspace.save_manifest()


def lock_path(root: Path) -> Path:
    """The lock file of the workspace at `root`: a hidden sibling, so it outlives `--force` replacing the folder."""
    root = Path(os.path.abspath(root))
    return root.with_name(f".{root.name}.lock")


@contextmanager
def workspace_lock(root: Path) -> Iterator[None]:
    """Hold the workspace's lock for the block, or refuse at once (one line) while another stage holds it.

    An OS file lock (flock) on a hidden sibling file: the kernel releases it when its process ends,
    however it ends, so a killed stage never leaves a stale lock. The file is removed on release; a
    locker that finds its file was removed meanwhile tries again. On entry, leftovers of a killed stage
    are cleaned up. Folders created for the lock file are removed again when no workspace appeared.
    """
    interrupts.check()
    path = lock_path(root)
    created = _make_parents(path.parent)
    try:
        descriptor = _acquire(path, root)
        try:
            os.pwrite(descriptor, f"{os.getpid()}\n".encode(), 0)
            recover_folder(Path(os.path.abspath(root)))
            if root.is_dir():
                remove_temporaries(root)
            yield
        finally:
            path.unlink(missing_ok=True)
            os.close(descriptor)  # releases the lock
    finally:
        if not root.exists():
            for folder in reversed(created):
                _remove_if_empty(folder)


@contextmanager
def reading_workspace(root: Path) -> Iterator[Workspace]:
    """Open the workspace at `root` for a read-only command, which needs no lock: when the lock is free (and can
    be created), it is held for the block and a killed stage's leftovers are cleaned up as `locked_workspace`
    does; when another stage holds it, or its folder is read-only, the workspace is read as it is."""
    root = Path(root)
    try:
        open_workspace(root)  # a one-line refusal before anything is created
    except AvatarPerfectError:
        _tidy_after_killed_stage(root)
        raise
    with ExitStack() as lock:
        locked = False
        try:
            lock.enter_context(workspace_lock(root))
            locked = True
        except LockUnavailable:
            pass
        workspace = open_workspace(root)
        if locked:
            workspace.remove_uncommitted()
        yield workspace


class LockUnavailable(AvatarPerfectError):
    """The workspace's lock is held by another stage or cannot be created (the message says which)."""


def _make_parents(folder: Path) -> list[Path]:
    """Create `folder` and its missing ancestors; returns the ones created, outermost first (a one-line error
    when they cannot be created)."""
    missing = []
    while not folder.exists() and folder != folder.parent:
        missing.append(folder)
        folder = folder.parent
    created = []
    try:
        for folder in reversed(missing):
            folder.mkdir()
            created.append(folder)
    except OSError as error:
        for done in reversed(created):
            _remove_if_empty(done)
        raise LockUnavailable(f"{folder}: cannot create the folder for the workspace's lock: {error.strerror or error}") from None
    return created


def _remove_if_empty(folder: Path) -> None:
    try:
        folder.rmdir()
    except OSError:
        pass  # not empty (something else appeared there) or already gone


def _tidy_after_killed_stage(root: Path) -> None:
    """Remove what a stage killed before its workspace appeared left beside `root` (its staging folder, or a
    retired workspace put back) and then its lock file, unless a stage holds the lock. Creates nothing."""
    path = lock_path(root)
    try:
        descriptor = os.open(path, os.O_RDWR)
    except OSError:
        return  # no lock file, or one this command may not touch
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        if os.stat(path).st_ino == os.fstat(descriptor).st_ino:
            recover_folder(Path(os.path.abspath(root)))
            path.unlink()
    except OSError:
        pass  # held by a running stage, or already removed
    finally:
        os.close(descriptor)


def refuse_if_busy(root: Path) -> None:
    """Raise the lock's one-line refusal when another stage holds the workspace at `root`; else return at
    once. A probe, not a lock: it imports nothing heavy, so the CLI calls it before loading torch."""
    try:
        descriptor = os.open(lock_path(root), os.O_RDONLY)
    except OSError:
        return  # no lock file: nobody holds it
    try:
        fcntl.flock(descriptor, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        raise _busy(root, _holder(descriptor)) from None
    finally:
        os.close(descriptor)


def _holder(descriptor: int) -> str:
    return os.pread(descriptor, 32, 0).decode(errors="replace").strip() or "?"


def _busy(root: Path, holder: str) -> AvatarPerfectError:
    return LockUnavailable(f"{root}: another avatarperfect stage (pid {holder}) is using this workspace; wait for it to finish")


def _acquire(path: Path, root: Path) -> int:
    """A descriptor of `path` holding its exclusive lock (see `workspace_lock`)."""
    while True:
        try:
            descriptor = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as error:
            raise LockUnavailable(
                f"{root}: cannot create the workspace's lock file {path}: {error.strerror or error} (its folder must be writable)"
            ) from None
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(descriptor)
            os.close(descriptor)
            raise _busy(root, holder) from None
        try:
            if os.stat(path).st_ino == os.fstat(descriptor).st_ino:
                return descriptor
        except FileNotFoundError:
            pass
        os.close(descriptor)  # the holder removed the file between our open and our lock


@contextmanager
def locked_workspace(root: Path) -> Iterator[Workspace]:
    """Open the workspace at `root` under its lock (see `workspace_lock`)."""
    with workspace_lock(root):
        workspace = open_workspace(root)
        workspace.remove_uncommitted()
        yield workspace
