"""Video outputs: frames streamed into an .mp4 or a folder of frame_0000.png, ... that appears only when complete.

- an .mp4 is encoded into a temporary file that replaces the output when the last frame is written (an
  existing .mp4 is replaced only with `force`);
- a new folder is filled in a hidden sibling and renamed into place;
- an existing folder must be empty or a previous frames output (only frame_NNNN.png files); its
  frame_NNNN.png files are replaced once all frames are written, and those beyond the new count removed.
  Any other folder is refused unless `force`, which writes the frames beside its other files (kept).
Nothing else is ever deleted.
"""

from __future__ import annotations

import os
import re
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import torch

from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.io.atomic import atomic_path, recover_folder, staging_dir
from avatarperfect_cli.io.images import write_image
from avatarperfect_cli.io.outputs import check_new_output, check_writable_folder

FRAME_NAME = re.compile(r"frame_(\d{4,})\.png")
FRAMES_STAGING = "avatarperfect-frames"  # frames are staged in OUTPUT/.avatarperfect-frames.*.tmp


def check_video_output(output: Path, force: bool = False) -> None:
    """Refuse, before any rendering, an output that a video may not be written to (see the module doc).

    output: an .mp4 file, or a folder for the frames (new, empty, or a previous frames output; another
    folder only with `force`).
    """
    if output.suffix.lower() == ".mp4":
        check_new_output(output, (".mp4",), force)
        return
    if output.suffix and not output.is_dir():
        raise AvatarPerfectError(f"{output}: give an .mp4 file or a folder for the frames")
    check_writable_folder(output)
    if output.is_dir() and not force:
        others = sorted(entry.name for entry in os.scandir(output) if not _is_frames_entry(entry))
        if others:
            more = f" and {len(others) - 1} more" if len(others) > 1 else ""
            raise AvatarPerfectError(
                f"{output}: the folder holds other files than frames ('{others[0]}'{more}); give a new or empty "
                "folder, or pass --force to write the frames beside them"
            )


def _is_frames_entry(entry: os.DirEntry) -> bool:
    """A frame_NNNN.png file, or a staging folder a killed render left."""
    if entry.name.startswith(f".{FRAMES_STAGING}.") and entry.name.endswith(".tmp"):
        return entry.is_dir(follow_symlinks=False)
    return bool(FRAME_NAME.fullmatch(entry.name)) and entry.is_file(follow_symlinks=False)


@contextmanager
def frame_writer(output: Path, width: int, height: int, fps: float) -> Iterator[Callable[[torch.Tensor], None]]:
    """A function that appends one frame (H, W, 3) in [0, 1] to the .mp4 or frames folder `output`, which
    appears complete when the block succeeds and not at all (or unchanged) when it fails."""
    try:
        if output.suffix.lower() == ".mp4":
            with _mp4_writer(output, width, height, fps) as write:
                yield write
        else:
            with _png_frames_writer(output) as write:
                yield write
    except OSError as error:  # e.g. the disk filled up
        raise InputFileError(output, f"cannot be written: {error.strerror or error}") from None


@contextmanager
def _mp4_writer(output: Path, width: int, height: int, fps: float) -> Iterator[Callable[[torch.Tensor], None]]:
    """Encode frames (OpenCV, mp4v) into a temporary file that replaces `output` when the block succeeds."""
    with atomic_path(output) as temporary:
        writer = cv2.VideoWriter(str(temporary), cv2.VideoWriter_fourcc(*"mp4v"), fps, (width, height))
        if not writer.isOpened():
            raise AvatarPerfectError(f"{output}: OpenCV cannot write mp4 video here")

        def write(frame: torch.Tensor) -> None:
            rgb = (frame.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()
            writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))

        try:
            yield write
        finally:
            writer.release()


@contextmanager
def _png_frames_writer(output: Path) -> Iterator[Callable[[torch.Tensor], None]]:
    """Write frame_0000.png, ... into a hidden staging folder; when the block succeeds it becomes the new
    folder `output`, or its frames replace those of the existing folder `output` (see the module doc)."""
    existing = output.is_dir()
    if existing:
        for leftover in output.glob(f".{FRAMES_STAGING}.*.tmp"):  # from a killed render
            shutil.rmtree(leftover, ignore_errors=True)
    else:
        recover_folder(output)  # the staging folder beside it that a killed render left
    staging = staging_dir(output / FRAMES_STAGING if existing else output)
    count = 0

    def write(frame: torch.Tensor) -> None:
        nonlocal count
        write_image(staging / f"frame_{count:04d}.png", frame.clamp(0, 1))
        count += 1

    try:
        yield write
        if existing:
            _move_frames(staging, output, count)
        else:
            os.rename(staging, output)  # fails rather than replace a folder that appeared meanwhile
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _move_frames(staging: Path, output: Path, count: int) -> None:
    """Move frames 0..count-1 from `staging` into `output`, then remove output's frames numbered count or more."""
    for index in range(count):
        name = f"frame_{index:04d}.png"
        os.replace(staging / name, output / name)
    for entry in os.scandir(output):
        match = FRAME_NAME.fullmatch(entry.name)
        if match and int(match[1]) >= count and entry.is_file(follow_symlinks=False):
            os.unlink(entry.path)
