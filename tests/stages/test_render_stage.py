"""Pieces of the render stage with exact answers."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.io import read_image, video, write_camera, write_gaussians
from avatarperfect_cli.render import Camera, look_at
from avatarperfect_cli.stages import render as stage
from avatarperfect_cli.stages.render import orbit_cameras, parse_background, render_avatar_views, render_ply
from tests.reliability import corpus


def project(camera: Camera, point: torch.Tensor) -> torch.Tensor:
    p = camera.world_to_camera[:3, :3] @ point + camera.world_to_camera[:3, 3]
    return (camera.K @ (p / p[2]))[:2]


def test_orbit_keeps_the_centre_in_place_and_turns_around_it():
    K = torch.tensor([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]])
    center = torch.tensor([0.1, 0.9, 0.2])
    start = Camera(K, look_at(torch.tensor([0.5, 1.2, 3.0]), center, torch.tensor([0.0, 1, 0])), 100, 80)
    cameras = orbit_cameras(start, center, 4)
    assert torch.allclose(cameras[0].world_to_camera, start.world_to_camera, atol=1e-6)
    up = -start.world_to_camera[1, :3]
    for camera in cameras:
        torch.testing.assert_close(project(camera, center), project(start, center), atol=1e-4, rtol=0)
        torch.testing.assert_close((camera.center - center).norm(), (start.center - center).norm())
        torch.testing.assert_close(torch.dot(camera.center - center, up), torch.dot(start.center - center, up), atol=1e-5, rtol=0)
    # A quarter turn apart: the horizontal offsets from the centre are perpendicular.
    flat = [(c.center - center) - torch.dot(c.center - center, up) * up for c in cameras[:2]]
    assert abs(float(torch.dot(flat[0], flat[1]))) < 1e-5 * float(flat[0].norm() ** 2)
    assert math.isclose(float(flat[0].norm()), float(flat[1].norm()), rel_tol=1e-5)


@pytest.mark.parametrize("text,expected", [("white", [1.0, 1, 1]), ("black", [0.0, 0, 0]), ("0.2,0.5,1", [0.2, 0.5, 1.0])])
def test_parse_background(text, expected):
    torch.testing.assert_close(parse_background(text), torch.tensor(expected))


@pytest.mark.parametrize("text", ["mauve", "1,2,3", "0.1,0.2"])
def test_parse_background_rejects(text):
    with pytest.raises(AvatarPerfectError, match="background"):
        parse_background(text)


def test_pose_render_needs_a_png(tmp_path: Path):
    with pytest.raises(AvatarPerfectError, match=r"\.png"):
        render_avatar_views(tmp_path, tmp_path / "out.jpg", pose=tmp_path / "pose.json")


# ------------------------------------------------------------------------ outputs: folders, pairs, streaming


@pytest.fixture
def avatar_files(tmp_path: Path) -> tuple[Path, Path]:
    """A tiny avatar PLY and a camera JSON that sees it, in tmp_path/inputs."""
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    corpus.avatar().save(inputs / "avatar.ply")
    write_camera(inputs / "camera.json", corpus.camera())
    return inputs / "avatar.ply", inputs / "camera.json"


def turntable(files: tuple[Path, Path], output: Path, frames: int = 3, force: bool = False) -> None:
    render_avatar_views(files[0], output, turntable=frames, camera_path=files[1], progress=False, force=force)


def contents(folder: Path) -> dict[str, bytes]:
    return {path.name: path.read_bytes() for path in sorted(folder.iterdir())}


def frame_names(count: int) -> list[str]:
    return [f"frame_{index:04d}.png" for index in range(count)]


def test_frames_go_to_a_new_folder_and_nothing_else_is_left(tmp_path: Path, avatar_files):
    turntable(avatar_files, tmp_path / "frames")
    assert list(contents(tmp_path / "frames")) == frame_names(3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames", "inputs"]


def test_a_folder_with_other_files_is_refused_before_rendering(tmp_path: Path, avatar_files, monkeypatch):
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "thesis.tex").write_text("precious")
    (folder / "frame_0000.png").write_bytes(b"mine too")
    monkeypatch.setattr(stage, "render_avatar", lambda *args: pytest.fail("rendered before refusing"))
    with pytest.raises(AvatarPerfectError, match="'thesis.tex'.*--force"):
        turntable(avatar_files, folder)
    assert contents(folder) == {"frame_0000.png": b"mine too", "thesis.tex": b"precious"}


def test_dot_never_empties_the_working_folder(tmp_path: Path, avatar_files, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    (work / "notes.txt").write_text("keep me")
    monkeypatch.chdir(work)
    with pytest.raises(AvatarPerfectError, match="other files than frames"):
        turntable(avatar_files, Path("."))
    assert contents(work) == {"notes.txt": b"keep me"}
    turntable(avatar_files, Path("."), force=True)
    assert list(contents(work)) == [*frame_names(3), "notes.txt"] and (work / "notes.txt").read_text() == "keep me"


def test_a_previous_frames_output_is_replaced_and_its_extra_frames_removed(tmp_path: Path, avatar_files):
    folder = tmp_path / "frames"
    turntable(avatar_files, tmp_path / "reference")  # the same render into a new folder, for comparison
    folder.mkdir()
    for name in frame_names(5):
        (folder / name).write_bytes(b"old frame")
    turntable(avatar_files, folder)
    assert contents(folder) == contents(tmp_path / "reference")


def test_force_writes_frames_beside_other_files(tmp_path: Path, avatar_files):
    folder = tmp_path / "mixed"
    folder.mkdir()
    (folder / "notes.txt").write_text("keep me")
    (folder / "frame_0009.png").write_bytes(b"a stale frame")
    turntable(avatar_files, folder, force=True)
    assert list(contents(folder)) == [*frame_names(3), "notes.txt"]


def test_an_interrupted_render_leaves_the_folder_as_it_was(tmp_path: Path, avatar_files, monkeypatch):
    folder = tmp_path / "frames"
    folder.mkdir()
    for name in frame_names(2):
        (folder / name).write_bytes(b"old frame")
    real_render = stage.render_avatar
    calls = []

    def render_then_interrupt(*args):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real_render(*args)

    monkeypatch.setattr(stage, "render_avatar", render_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        turntable(avatar_files, folder)
    assert contents(folder) == {name: b"old frame" for name in frame_names(2)}  # no staging folder left either
    with pytest.raises(KeyboardInterrupt):
        calls.clear()
        turntable(avatar_files, tmp_path / "new.mp4")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames", "inputs"]


class RecordingVideoWriter:
    """Stands in for cv2.VideoWriter: records each frame written into the shared event log."""

    events: list[str] = []

    def __init__(self, path: str, fourcc: int, fps: float, size: tuple[int, int]) -> None:
        Path(path).write_bytes(b"video")
        self.size = size

    def isOpened(self) -> bool:
        return True

    def write(self, frame) -> None:
        assert frame.shape == (self.size[1], self.size[0], 3)
        self.events.append("write")

    def release(self) -> None:
        pass


@pytest.mark.parametrize("output", ["frames", "video.mp4"])
def test_each_frame_is_written_as_soon_as_it_is_rendered(tmp_path: Path, avatar_files, monkeypatch, output: str):
    """Streaming: frame k reaches the encoder (or the folder) before frame k + 1 is rendered."""
    events = RecordingVideoWriter.events = []
    real_render, real_write_image = stage.render_avatar, video.write_image

    def render(*args):
        events.append("render")
        return real_render(*args)

    def write_image(*args):
        events.append("write")
        real_write_image(*args)

    monkeypatch.setattr(stage, "render_avatar", render)
    monkeypatch.setattr(video, "write_image", write_image)
    monkeypatch.setattr(video.cv2, "VideoWriter", RecordingVideoWriter)
    turntable(avatar_files, tmp_path / output, frames=4)
    assert events == ["render", "write"] * 4


def test_image_outputs_are_checked_before_the_inputs_are_read(tmp_path: Path):
    (tmp_path / "out.png").mkdir()
    with pytest.raises(InputFileError, match="out.png: is a folder"):
        render_ply(tmp_path / "missing.ply", tmp_path / "missing.json", tmp_path / "out.png")
    (tmp_path / "b_alpha.png").mkdir()
    with pytest.raises(InputFileError, match="b_alpha.png: is a folder"):
        render_avatar_views(tmp_path / "missing.ply", tmp_path / "b.png", pose=tmp_path / "missing.json")
    (tmp_path / "v.mp4").mkdir()
    with pytest.raises(InputFileError, match="v.mp4: is a folder"):
        render_avatar_views(tmp_path / "missing.ply", tmp_path / "v.mp4", turntable=2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b_alpha.png", "out.png", "v.mp4"]


@pytest.mark.parametrize("fps", [0.0, -5.0, math.nan])
def test_frame_rate_must_be_positive(tmp_path: Path, fps: float):
    with pytest.raises(AvatarPerfectError, match="--fps"):
        render_avatar_views(tmp_path / "missing.ply", tmp_path / "v.mp4", turntable=2, fps=fps)


def test_a_camera_that_sees_nothing_gives_one_warning_line(tmp_path: Path, capsys):
    write_gaussians(tmp_path / "scene.ply", corpus.gaussians())
    write_camera(tmp_path / "front.json", corpus.camera())
    away = corpus.camera()
    away.world_to_camera = look_at(torch.tensor([0.0, 0.0, 3.0]), torch.tensor([0.0, 0.0, 6.0]), torch.tensor([0.0, 1.0, 0.0]))
    write_camera(tmp_path / "away.json", away)
    render_ply(tmp_path / "scene.ply", tmp_path / "front.json", tmp_path / "front.png")
    assert capsys.readouterr().err == ""
    render_ply(tmp_path / "scene.ply", tmp_path / "away.json", tmp_path / "away.png")
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("warning: ") and "away.png" in lines[0]
    assert read_image(tmp_path / "away_alpha.png", mode="L").max() == 0  # the warning told the truth


# ------------------------------------------------------------------------------------ motions from other tools


def test_a_y_down_motion_renders_like_the_y_up_original(tmp_path: Path, avatar_files):
    """InstantAvatar's demo motion lives in the camera's y-down frame: detected, it renders as the y-up file
    does; read as y-up (--up y), it renders upside down."""
    from avatarperfect_cli.body import axis_angle_to_matrix
    from avatarperfect_cli.io.motion import write_motion
    from avatarperfect_cli.rotations import matrix_to_axis_angle

    frames = 3
    body_pose = torch.zeros(frames, 24, 3)
    body_pose[:, 0] = torch.tensor([[0.1, 0.4, 0.0], [0.2, 0.6, 0.1], [0.0, 0.9, -0.2]])  # turning, tilting
    transl = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.05, 0.0], [0.2, -0.05, 0.1]])
    write_motion(tmp_path / "y_up.npz", body_pose, transl)
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0]))  # the avatar's rest pelvis is the origin: roots turn with the world
    y_down = body_pose.clone()
    y_down[:, 0] = matrix_to_axis_angle(flip @ axis_angle_to_matrix(body_pose[:, 0]))
    write_motion(tmp_path / "y_down.npz", y_down, transl @ flip.T)

    def render(motion: str, up: str | None = None) -> torch.Tensor:
        out = tmp_path / f"{motion}-{up}"
        motion_file = tmp_path / f"{motion}.npz"
        render_avatar_views(avatar_files[0], out, motion=motion_file, camera_path=avatar_files[1], progress=False, up=up)
        return torch.stack([read_image(out / name) for name in frame_names(frames)])

    original, detected, misread = render("y_up"), render("y_down"), render("y_down", "y")
    assert (original < 0.9).any()  # the avatar shows
    assert (detected - original).abs().max() <= 2 / 255
    assert (misread - original).abs().max() > 0.5


def test_up_needs_a_motion_and_a_known_axis(tmp_path: Path, avatar_files):
    with pytest.raises(AvatarPerfectError, match="--up x"):
        render_avatar_views(avatar_files[0], tmp_path / "out", turntable=2, camera_path=avatar_files[1], up="x")
    with pytest.raises(AvatarPerfectError, match="--up y"):
        render_avatar_views(avatar_files[0], tmp_path / "out", turntable=2, camera_path=avatar_files[1], up="y")
