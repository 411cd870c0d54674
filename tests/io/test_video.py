"""Video outputs: frames folders that appear complete or not at all, the folders they may go to, and .mp4 files
decoded back with OpenCV."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.io import read_image
from avatarperfect_cli.io.video import check_video_output, frame_writer

HEIGHT, WIDTH = 24, 32


def frames(count: int, seed: int = 0) -> list[torch.Tensor]:
    """`count` frames (H, W, 3), each one flat colour drawn at random: 8-bit PNGs keep them to 0.5 / 255."""
    colours = torch.rand(count, 3, generator=torch.Generator().manual_seed(seed))
    return [colour.expand(HEIGHT, WIDTH, 3).clone() for colour in colours]


def write_all(output: Path, images: list[torch.Tensor]) -> None:
    with frame_writer(output, WIDTH, HEIGHT, 10.0) as write:
        for image in images:
            write(image)


def names(count: int) -> list[str]:
    return [f"frame_{index:04d}.png" for index in range(count)]


def test_frames_fill_a_new_folder_in_order(tmp_path: Path):
    images = frames(3)
    write_all(tmp_path / "out", images)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == names(3)
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no staging folder left beside it
    for name, image in zip(names(3), images):
        torch.testing.assert_close(read_image(tmp_path / "out" / name), image, atol=0.5 / 255 + 1e-6, rtol=0)


def test_a_previous_frames_output_gets_the_new_frames_and_loses_the_extra_ones(tmp_path: Path):
    folder = tmp_path / "out"
    folder.mkdir()
    for name in names(5):
        (folder / name).write_bytes(b"old frame")
    (folder / "frame_0007.png").mkdir()  # a folder, not a frame file: left alone
    write_all(folder, frames(2))
    write_all(tmp_path / "reference", frames(2))
    assert sorted(p.name for p in folder.iterdir()) == [*names(2), "frame_0007.png"]
    for name in names(2):
        assert (folder / name).read_bytes() == (tmp_path / "reference" / name).read_bytes()


@pytest.mark.parametrize("existing", [False, True])
def test_a_failing_block_leaves_no_trace(tmp_path: Path, existing: bool):
    folder = tmp_path / "out"
    if existing:
        folder.mkdir()
        (folder / "frame_0000.png").write_bytes(b"old frame")
    before = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*"))
    with pytest.raises(KeyboardInterrupt), frame_writer(folder, WIDTH, HEIGHT, 10.0) as write:
        write(frames(1)[0])
        raise KeyboardInterrupt
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")) == before
    if existing:
        assert (folder / "frame_0000.png").read_bytes() == b"old frame"


def test_only_new_empty_or_frames_folders_are_accepted_without_force(tmp_path: Path):
    check_video_output(tmp_path / "new")
    frames_folder = tmp_path / "frames"
    frames_folder.mkdir()
    check_video_output(frames_folder)  # empty
    (frames_folder / "frame_0003.png").write_bytes(b"")
    (frames_folder / ".avatarperfect-frames.x1.tmp").mkdir()  # what a killed render leaves
    check_video_output(frames_folder)
    (frames_folder / "notes.txt").write_text("mine")
    (frames_folder / "frame_12.png").write_bytes(b"")  # too few digits: not a frame
    with pytest.raises(AvatarPerfectError, match=r"other files than frames \('frame_12.png' and 1 more\).*--force"):
        check_video_output(frames_folder)
    check_video_output(frames_folder, force=True)
    with pytest.raises(AvatarPerfectError, match="give an .mp4 file or a folder"):
        check_video_output(tmp_path / "video.avi")


def test_an_existing_mp4_is_replaced_only_with_force(tmp_path: Path):
    video = tmp_path / "video.mp4"
    check_video_output(video)
    video.write_bytes(b"mine")
    with pytest.raises(InputFileError):
        check_video_output(video)
    check_video_output(video, force=True)


def test_mp4_holds_every_frame_at_its_size_and_colour(tmp_path: Path):
    images = frames(4, seed=1)
    video = tmp_path / "video.mp4"
    video.write_bytes(b"replaced once the last frame is written")
    write_all(video, images)
    capture = cv2.VideoCapture(str(video))
    decoded = []
    while True:
        ok, bgr = capture.read()
        if not ok:
            break
        decoded.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    capture.release()
    assert len(decoded) == 4 and decoded[0].shape == (HEIGHT, WIDTH, 3)
    for rgb, image in zip(decoded, images):  # lossy, but a flat colour survives to a few levels
        assert np.abs(rgb.astype(float) - image.numpy() * 255).mean() < 6.0
    assert [p.name for p in tmp_path.iterdir()] == ["video.mp4"]
