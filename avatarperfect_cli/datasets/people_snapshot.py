"""Monocular videos in the People-Snapshot layout, as preprocessed by InstantAvatar and GART.

Layout under the dataset root:

    cameras.npz                 intrinsic (3, 3), extrinsic (4, 4) world->camera (OpenCV), height, width
    images/image_%04d.png       frames, numbered by frame id
    masks/mask_%04d.npy         uint8 0/1 subject masks (or masks/mask_%04d.png with 0/255)
    poses.npz                   betas (10,) or (1, 10), thetas (N, 72), transl (N, 3)
    poses_optimized.npz         refined poses; like poses.npz, or global_orient (N, 3) + body_pose (N, 69)
    poses/anim_nerf_{split}.npz per-split poses (InstantAvatar "refine"), same keys as above
    subject.json                optional avatarperfect extension: {"body_model": "anny" | "smpl", ...}

Which pose file: with pose_source "auto", the split's file poses/anim_nerf_{split}.npz when there is one,
else poses_optimized.npz, else poses.npz; when several are present the choice is reported in
`VideoDataset.notes`. A pose_source path picks one file (relative to the root, or absolute).

Which pose row belongs to which frame:
- poses.npz, poses_optimized.npz and any other whole-sequence file: row i is frame i (as in InstantAvatar),
  so the file needs more rows than the largest selected frame id;
- split files (`anim_nerf_*.npz`) hold one row per frame of their split, in order, but do not store which
  frames those are (InstantAvatar's configs give start/end/skip). With an explicit frame range, its row
  count must equal the number of selected frames and row k is the k-th selected frame. Without one:
  1. a row per image: every image;
  2. a folder named like one of InstantAvatar's People-Snapshot subjects (INSTANTAVATAR_SPLITS) whose
     row count matches that config: the config's frames;
  3. otherwise InstantAvatar's convention, assumed: the train split starts at the first image and the test
     split (val: its first frame) follows it, both with the one step round(images / (train + test rows)),
     counted over the sorted images like InstantAvatar's loader.
  Cases 2 and 3 are a guess and say so in `VideoDataset.notes`; a split that does not fit the images is an
  error naming the file, rather than a silent misalignment.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import tempfile
import threading
import zipfile
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import cv2
import numpy as np
import torch
from PIL import Image

from avatarperfect_cli.errors import InputFileError
from avatarperfect_cli.io.atomic import staging_dir
from avatarperfect_cli.io.camera_json import check_camera_values
from avatarperfect_cli.render.camera import Camera

NUM_BETAS = 10
SPLITS = ("train", "val", "test")
_IMAGE_NAME = re.compile(r"image_(\d{4,})\.png")
_MAX_THREADS = 8

SPLIT_PREFIX = "anim_nerf_"


def _instantavatar_config(train: str, test: str) -> dict[str, FrameRange]:
    """A subject's splits as InstantAvatar's confs/dataset/peoplesnapshot/*.yaml give them (val: one frame)."""
    train_range, test_range = FrameRange.parse(train), FrameRange.parse(test)
    val_range = FrameRange(test_range.start, test_range.start, test_range.step)
    return {"train": train_range, "val": val_range, "test": test_range}


_T = TypeVar("_T")
_R = TypeVar("_R")


@dataclass(frozen=True)
class FrameRange:
    """Frame ids start, start + step, ... up to `end` inclusive (e.g. male-3-casual trains on 0..455 step 4)."""

    start: int
    end: int
    step: int = 1

    def __post_init__(self) -> None:
        if self.start < 0:
            raise ValueError(f"frame range start must be >= 0, got {self.start}")
        if self.step < 1:
            raise ValueError(f"frame range step must be >= 1, got {self.step}")

    def frame_ids(self) -> np.ndarray:
        """(T,) int64 selected frame ids; empty when end < start."""
        return np.arange(self.start, self.end + 1, self.step, dtype=np.int64)

    def __str__(self) -> str:
        return f"{self.start}..{self.end} step {self.step}"

    @classmethod
    def parse(cls, text: str) -> FrameRange:
        """'START:END' or 'START:END:STEP' (END inclusive); ValueError with a readable message."""
        parts = text.split(":")
        try:
            numbers = [int(part) for part in parts]
        except ValueError:
            numbers = []
        if len(numbers) not in (2, 3):
            raise ValueError(f"frame range '{text}' is not START:END or START:END:STEP")
        return cls(*numbers)


# start:end:skip (end inclusive) of InstantAvatar's public People-Snapshot configs, indices into the sorted images.
INSTANTAVATAR_SPLITS: dict[str, dict[str, FrameRange]] = {
    "male-3-casual": _instantavatar_config("0:455:4", "456:675:4"),
    "female-3-casual": _instantavatar_config("0:445:4", "446:647:4"),
    "female-4-casual": _instantavatar_config("0:335:4", "335:523:4"),
    "male-4-casual": _instantavatar_config("0:659:6", "660:872:6"),
}


@dataclass
class VideoDataset:
    """T frames of one subject seen by a fixed camera.

    images:    (T, H, W, 3) float32 RGB in [0, 1], composited onto white with the mask
    masks:     (T, H, W) bool, True on the subject
    body_pose: (T, 24, 3) float32 SMPL axis-angle, radians; joint 0 is the global orientation
    transl:    (T, 3) float32 root translation, metres, world frame
    betas:     (10,) float32 SMPL shape coefficients
    camera:    the fixed camera, sized for `images`
    frame_ids: (T,) int64 frame numbers of the images
    subject:   the parsed subject.json (body model and shape), or None
    pose_file: the pose file read, relative to the dataset root when inside it
    notes:     one line each about a choice the loader made that the user may want to override
               (which of several pose files, which frames a split file covers)
    filmed:    (T, H, W, 3) uint8 RGB, the frames as filmed (not composited), or None
    """

    images: torch.Tensor
    masks: torch.Tensor
    body_pose: torch.Tensor
    transl: torch.Tensor
    betas: torch.Tensor
    camera: Camera
    frame_ids: torch.Tensor
    subject: dict[str, Any] | None
    pose_file: str = "poses.npz"
    notes: tuple[str, ...] = ()
    filmed: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.frame_ids.shape[0])


def load_people_snapshot(
    root: Path,
    frames: FrameRange | None = None,
    split: str | None = None,
    downscale: int = 1,
    pose_source: str = "auto",
    with_images: bool = True,
) -> VideoDataset:
    """Load a People-Snapshot folder.

    frames:      frame ids to load; None loads every image in images/
    split:       "train", "val" or "test"; with pose_source "auto" it selects poses/anim_nerf_{split}.npz
                 when that file exists (see the module doc for the frames a split file covers)
    downscale:   integer factor; the size becomes round(W / d) x round(H / d). Images are averaged over
                 pixel areas (cv2.INTER_AREA) after compositing, masks are area-averaged and kept where >= 0.5,
                 and K's rows scale by the exact size ratio per axis (pixel centres at +0.5; this equals
                 Camera.scaled(1 / d) when d divides the size)
    pose_source: "auto" (the split file if any, else poses_optimized.npz, else poses.npz) or a path
                 relative to `root` (or absolute)
    with_images: False reads only the poses and the camera (`images` and `masks` are then empty)
    Raises InputFileError naming the offending file for any missing or malformed input.
    """
    if split is not None and split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    if downscale < 1:
        raise ValueError(f"downscale must be >= 1, got {downscale}")
    root = Path(root)
    if not root.is_dir():
        raise InputFileError(root, "dataset folder not found")

    camera = _read_camera(root / "cameras.npz")
    available = _available_frames(root / "images")
    pose_path, notes = _pose_path(root, split, pose_source)
    thetas, all_transl, betas = _read_pose_arrays(pose_path)
    if _is_split_file(pose_path):
        if frames is None:
            frame_ids, frames_note = _split_frames(root, pose_path, len(thetas), available)
            notes += [frames_note] if frames_note else []
        else:
            frame_ids = _select_frames(root / "images", available, frames)
        rows = _split_rows(pose_path, len(thetas), frame_ids)
    else:
        frame_ids = _select_frames(root / "images", available, frames)
        rows = _sequence_rows(pose_path, len(thetas), frame_ids)
    body_pose = thetas[rows].reshape(-1, 24, 3).astype(np.float32)
    transl = all_transl[rows].astype(np.float32)
    subject = _read_subject(root / "subject.json")
    out_camera = downscaled_camera(camera, downscale)
    described = {"subject": subject, "pose_file": _relative_name(pose_path, root), "notes": tuple(notes)}
    if not with_images:
        return VideoDataset(
            images=torch.empty(0, out_camera.height, out_camera.width, 3),
            masks=torch.empty(0, out_camera.height, out_camera.width, dtype=torch.bool),
            body_pose=torch.from_numpy(body_pose),
            transl=torch.from_numpy(transl),
            betas=torch.from_numpy(betas),
            camera=out_camera,
            frame_ids=torch.from_numpy(frame_ids),
            **described,
        )

    out_width, out_height = out_camera.width, out_camera.height
    images = np.empty((len(frame_ids), out_height, out_width, 3), dtype=np.float32)
    filmed = np.empty((len(frame_ids), out_height, out_width, 3), dtype=np.uint8)
    masks = np.empty((len(frame_ids), out_height, out_width), dtype=bool)
    full_size = (out_width, out_height) == (camera.width, camera.height)

    def load_frame(index: int) -> None:
        frame = int(frame_ids[index])
        image_path = root / "images" / f"image_{frame:04d}.png"
        image = _read_image(image_path, camera)
        mask = _read_mask(root / "masks", frame, camera)
        composited = images[index] if full_size else np.empty((camera.height, camera.width, 3), np.float32)
        np.multiply(image, np.float32(1 / 255), out=composited, dtype=np.float32)
        np.copyto(composited, np.float32(1), where=~mask[:, :, None])
        if full_size:
            masks[index], filmed[index] = mask, image
        else:
            size = (out_width, out_height)
            images[index] = cv2.resize(composited, size, interpolation=cv2.INTER_AREA)
            filmed[index] = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
            masks[index] = cv2.resize(mask.astype(np.float32), size, interpolation=cv2.INTER_AREA) >= 0.5

    _parallel_map(load_frame, range(len(frame_ids)))

    return VideoDataset(
        images=torch.from_numpy(images),
        masks=torch.from_numpy(masks),
        body_pose=torch.from_numpy(body_pose),
        transl=torch.from_numpy(transl),
        betas=torch.from_numpy(betas),
        camera=out_camera,
        frame_ids=torch.from_numpy(frame_ids),
        **described,
        filmed=torch.from_numpy(filmed),
    )


def write_people_snapshot(
    root: Path,
    images: np.ndarray | Sequence[np.ndarray],
    masks: np.ndarray,
    body_pose: np.ndarray | torch.Tensor,
    transl: np.ndarray | torch.Tensor,
    camera: Camera,
    betas: np.ndarray | torch.Tensor | None = None,
    subject: dict[str, Any] | None = None,
) -> None:
    """Write frames 0..T-1 as a People-Snapshot folder at `root`, all at once.

    images:    (T, H, W, 3) uint8 RGB, or T frames (H, W, 3) (never stacked: a long video is not held twice),
               written as deterministic PNGs images/image_%04d.png
    masks:     (T, H, W) bool, written as uint8 0/1 masks/mask_%04d.npy
    body_pose: (T, 24, 3) SMPL axis-angle, radians, joint 0 the global orientation (poses.npz "thetas")
    transl:    (T, 3) metres
    camera:    the fixed camera; its size must match the images
    betas:     (10,) SMPL shape, zeros when None
    subject:   written to subject.json when given
    The folder is built next to `root` and renamed into place; an existing dataset at `root` is replaced.
    """
    masks = np.asarray(masks)
    body_pose = _as_numpy(body_pose).astype(np.float32)
    transl = _as_numpy(transl).astype(np.float32)
    betas = np.zeros(NUM_BETAS, np.float32) if betas is None else _as_numpy(betas).astype(np.float32).reshape(-1)
    count = len(images)
    expected = {
        "masks": (masks, (count, camera.height, camera.width)),
        "body_pose": (body_pose, (count, 24, 3)),
        "transl": (transl, (count, 3)),
        "betas": (betas, (NUM_BETAS,)),
    }
    for name, (array, shape) in expected.items():
        if array.shape != shape:
            raise ValueError(f"{name} has shape {array.shape}, expected {shape}")
    for index, image in enumerate(images):
        if image.shape != (camera.height, camera.width, 3) or image.dtype != np.uint8:
            raise ValueError(f"image {index} is {image.dtype} {image.shape}, expected uint8 {(camera.height, camera.width, 3)}")
    if masks.dtype != np.bool_:
        raise ValueError(f"masks must be bool, got {masks.dtype}")

    root = Path(root)
    check_dataset_output(root)
    staging = staging_dir(root)
    try:
        (staging / "images").mkdir()
        (staging / "masks").mkdir()

        def write_frame(index: int) -> None:
            image_path = staging / "images" / f"image_{index:04d}.png"
            Image.fromarray(images[index]).save(image_path, format="PNG", compress_level=6)  # no tIME chunk
            np.save(staging / "masks" / f"mask_{index:04d}.npy", masks[index].astype(np.uint8))

        _parallel_map(write_frame, range(count))
        np.savez(
            staging / "cameras.npz",
            intrinsic=camera.K.detach().cpu().double().numpy(),
            extrinsic=camera.world_to_camera.detach().cpu().double().numpy(),
            height=np.int64(camera.height),
            width=np.int64(camera.width),
        )
        np.savez(staging / "poses.npz", betas=betas, thetas=body_pose.reshape(count, 72), transl=transl)
        if subject is not None:
            (staging / "subject.json").write_text(json.dumps(subject, indent=2, sort_keys=True) + "\n")
        _move_into_place(staging, root)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise


# ----------------------------------------------------------------------------------------------- reading


def downscaled_camera(camera: Camera, downscale: int) -> Camera:
    """The camera for images of size round(W / d) x round(H / d); K's rows scale by the exact size ratio."""
    width, height = max(1, round(camera.width / downscale)), max(1, round(camera.height / downscale))
    K = camera.K.clone()
    K[0] *= width / camera.width
    K[1] *= height / camera.height
    return Camera(K, camera.world_to_camera, width, height)


def read_dataset_camera(root: Path) -> Camera:
    """The camera of a People-Snapshot folder (its cameras.npz) at the images' native size."""
    return _read_camera(Path(root) / "cameras.npz")


def _read_camera(path: Path) -> Camera:
    """The camera of cameras.npz, validated like a camera JSON (`check_camera_values`)."""
    data = _load_npz(path, "camera file")
    K = torch.from_numpy(_array(data, "intrinsic", path, (3, 3)))
    world_to_camera = torch.from_numpy(_array(data, "extrinsic", path, (4, 4)))
    size = {}
    for key in ("height", "width"):
        value = _array(data, key, path, None)
        if value.size != 1 or not float(value.reshape(-1)[0]).is_integer() or value.reshape(-1)[0] < 1:
            raise InputFileError(path, f"{key} must be one positive integer, got {value.reshape(-1)[:4].tolist()}")
        size[key] = int(value.reshape(-1)[0])
    check_camera_values(K, world_to_camera, size["width"], size["height"], path, ("'intrinsic'", "'extrinsic'"))
    return Camera(K.float(), world_to_camera.float(), size["width"], size["height"])


def _available_frames(images_dir: Path) -> np.ndarray:
    """(F,) int64 sorted ids of the frames that have an image_%04d.png in `images_dir`."""
    try:
        names = [entry.name for entry in os.scandir(images_dir)]
    except OSError:
        raise InputFileError(images_dir, "image folder not found") from None
    matches = (_IMAGE_NAME.fullmatch(name) for name in names)
    # Only canonical names count, so that image_0001.png and image_00001.png cannot both be frame 1.
    available = sorted(int(m[1]) for m in matches if m and m[0] == f"image_{int(m[1]):04d}.png")
    if not available:
        raise InputFileError(images_dir, "no images named image_%04d.png")
    return np.asarray(available, dtype=np.int64)


def _select_frames(images_dir: Path, available: np.ndarray, frames: FrameRange | None) -> np.ndarray:
    """(T,) int64 ids of the frames to load; each has an image in `images_dir` (`available`)."""
    if frames is None:
        return available
    selected = frames.frame_ids()
    if selected.size == 0:
        raise InputFileError(images_dir, f"frame range {frames} selects no frames")
    if selected[-1] > available[-1]:
        problem = f"frame range {frames} reaches frame {selected[-1]}, past the last image (frame {available[-1]})"
        raise InputFileError(images_dir, problem)
    missing = np.setdiff1d(selected, available)
    if missing.size:
        raise InputFileError(images_dir / f"image_{missing[0]:04d}.png", "image missing for a selected frame")
    return selected


def _pose_path(root: Path, split: str | None, pose_source: str) -> tuple[Path, list[str]]:
    """The pose file to read, and a note naming the other pose files when "auto" chose among several."""
    if pose_source != "auto":
        path = root / pose_source
        if not path.is_file():
            raise InputFileError(path, "pose file missing")
        return path, []
    candidates = [root / "poses" / f"{SPLIT_PREFIX}{split}.npz"] if split else []
    candidates += [root / "poses_optimized.npz", root / "poses.npz"]
    present = [path for path in candidates if path.is_file()]
    if not present:
        others = ", ".join(str(path.relative_to(root)) for path in candidates[:-1])
        split_files = sorted(path.name for path in (root / "poses").glob(f"{SPLIT_PREFIX}*.npz"))
        hint = f"; there are split files ({', '.join(split_files)}): name one with --poses" if split_files else ""
        raise InputFileError(root / "poses.npz", f"pose file missing (also looked for {others}){hint}")
    chosen = present[0]
    notes = []
    if len(present) > 1:
        others = ", ".join(_relative_name(path, root) for path in present[1:])
        notes.append(f"{root}: poses from {_relative_name(chosen, root)} (also there: {others}; --poses picks another)")
    return chosen, notes


def _is_split_file(path: Path) -> bool:
    return path.name.startswith(SPLIT_PREFIX)


def _relative_name(path: Path, root: Path) -> str:
    """`path` relative to `root` (POSIX separators) when inside it, else as given."""
    try:
        return path.relative_to(root).as_posix()
    except ValueError:
        return str(path)


def _read_pose_arrays(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """thetas (N, 72) and transl (N, 3) float64, betas (10,) float32, from a pose file (any layout)."""
    data = _load_npz(path, "pose file")
    if "thetas" in data:
        thetas = _array(data, "thetas", path, (None, 72))
    elif "global_orient" in data and "body_pose" in data:
        global_orient = _array(data, "global_orient", path, (None, 3))
        joints = _array(data, "body_pose", path, (global_orient.shape[0], 69))
        thetas = np.concatenate([global_orient, joints], axis=1)
    else:
        raise InputFileError(path, "holds neither 'thetas' nor 'global_orient' + 'body_pose'")
    transl = _array(data, "transl", path, (thetas.shape[0], 3))
    betas = _array(data, "betas", path, None)
    if betas.shape not in ((NUM_BETAS,), (1, NUM_BETAS)):
        raise InputFileError(path, f"'betas' has shape {betas.shape}, expected (10,) or (1, 10)")
    return thetas, transl, betas.reshape(NUM_BETAS).astype(np.float32)


def _sequence_rows(path: Path, rows: int, frame_ids: np.ndarray) -> np.ndarray:
    """Rows of a whole-sequence pose file for `frame_ids`: row i is frame i."""
    if rows <= frame_ids.max():
        raise InputFileError(path, f"holds {rows} pose rows, fewer than needed for frame {frame_ids.max()}")
    return frame_ids


def _split_rows(path: Path, rows: int, frame_ids: np.ndarray) -> np.ndarray:
    """Rows of a split file for its frames `frame_ids`: one row per frame, in order."""
    if rows != len(frame_ids):
        raise InputFileError(
            path,
            f"split file holds {rows} pose rows for {len(frame_ids)} selected frames; "
            "select exactly the split's frames (its rows follow them in order)",
        )
    return np.arange(rows)


def _split_frames(root: Path, path: Path, rows: int, available: np.ndarray) -> tuple[np.ndarray, str | None]:
    """The frames a split file's `rows` rows belong to, when no frame range was given (the module doc's
    rules 1 to 3), and a note when that is a guess. `available`: (F,) sorted ids of the images."""
    if rows == len(available):
        return available, None
    if rows > len(available):
        problem = f"holds {rows} pose rows, more than the {len(available)} images: it is not this video's split"
        raise InputFileError(path, problem)
    split = path.stem.removeprefix(SPLIT_PREFIX)
    unknown = f"holds {rows} pose rows for {len(available)} images, and a split file does not store which frames they are"
    known = INSTANTAVATAR_SPLITS.get(root.resolve().name, {}).get(split)
    if known is not None and len(known.frame_ids()) == rows and known.end < len(available):
        indices, source = known.frame_ids(), f"InstantAvatar's {root.resolve().name} config"
    else:
        counts = {name: rows if name == split else _split_row_count(root, name) for name in ("train", "test")}
        if split != "train" and counts["test"] == 0:  # val (or another split) with no test file: it follows train
            counts["test"] = rows
        step = round(len(available) / sum(counts.values()))
        start = 0 if split == "train" else counts["train"] * step
        indices = start + step * np.arange(rows)
        if step < 1 or indices[-1] >= len(available):
            raise InputFileError(path, f"{unknown}; give them with --frames START:END:STEP (InstantAvatar's start/end/skip)")
        source = "the train split from the first image, the test split after it, one step (InstantAvatar's convention)"
    frame_ids = available[indices]
    chosen = FrameRange(int(frame_ids[0]), int(frame_ids[-1]), int(indices[1] - indices[0]) if rows > 1 else 1)
    described = chosen if np.array_equal(frame_ids, chosen.frame_ids()) else f"image indices {indices[0]}..{indices[-1]}"
    return frame_ids, f"{path}: {unknown}; assuming frames {described} from {source}; --frames overrides"


def _split_row_count(root: Path, split: str) -> int:
    """Rows of poses/anim_nerf_{split}.npz, 0 when there is no such file."""
    path = root / "poses" / f"{SPLIT_PREFIX}{split}.npz"
    return len(_read_pose_arrays(path)[0]) if path.is_file() else 0


def _read_subject(path: Path) -> dict[str, Any] | None:
    if not path.exists():
        return None
    try:
        subject = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise InputFileError(path, f"unreadable JSON ({error})") from None
    if not isinstance(subject, dict) or not isinstance(subject.get("body_model"), str):
        raise InputFileError(path, "expected a JSON object with a 'body_model' string")
    return subject


def _decode_8bit(path: Path, mode: str) -> np.ndarray | None:
    """(H, W, 3) RGB ("RGB") or (H, W) gray ("L") uint8 pixels of an image file, None when it cannot be decoded.

    16-bit images keep their high byte and alpha is dropped, as OpenCV's IMREAD_COLOR / IMREAD_GRAYSCALE do.
    Pillow decodes rather than OpenCV because libpng, inside OpenCV, prints damage reports on stderr.
    """
    try:
        with Image.open(path) as image:
            image.load()
            if image.mode in ("I", "I;16", "I;16B", "I;16L"):
                gray = (np.asarray(image).astype(np.int64).clip(0, 65535) >> 8).astype(np.uint8)
                return np.repeat(gray[:, :, None], 3, axis=2) if mode == "RGB" else gray
            return np.asarray(image.convert(mode))
    except (OSError, ValueError, Image.DecompressionBombError):
        return None


def _read_image(path: Path, camera: Camera) -> np.ndarray:
    """(H, W, 3) uint8 RGB."""
    image = _decode_8bit(path, "RGB")
    if image is None:
        raise InputFileError(path, "image unreadable")
    if image.shape[:2] != (camera.height, camera.width):
        raise InputFileError(
            path, f"image is {image.shape[1]}x{image.shape[0]}, cameras.npz says {camera.width}x{camera.height}"
        )
    return image


# np.load parses a .npy header with ast.literal_eval, and CPython 3.11's AST constructor keeps one recursion
# counter per interpreter: two threads parsing at once can fail with "SystemError: AST constructor recursion
# depth mismatch" (python/cpython#106905; seen once in CI while the frame loader's threads read masks).
_NPY_HEADER_LOCK = threading.Lock()


def _read_mask(masks_dir: Path, frame: int, camera: Camera) -> np.ndarray:
    """(H, W) bool subject mask of `frame`, from mask_%04d.npy (0/1) or else mask_%04d.png (0/255)."""
    npy_path = masks_dir / f"mask_{frame:04d}.npy"
    png_path = masks_dir / f"mask_{frame:04d}.png"
    if npy_path.is_file():
        path, on_value = npy_path, 1
        try:
            with _NPY_HEADER_LOCK:
                mask = np.load(npy_path, allow_pickle=False)
        except (OSError, ValueError, EOFError):
            raise InputFileError(path, "mask unreadable") from None
    elif png_path.is_file():
        path, on_value = png_path, 255
        mask = _decode_8bit(png_path, "L")
        if mask is None:
            raise InputFileError(path, "mask unreadable")
    else:
        raise InputFileError(npy_path, "mask missing (no .npy or .png mask for this frame)")
    if mask.shape != (camera.height, camera.width):
        raise InputFileError(path, f"mask has shape {mask.shape}, expected ({camera.height}, {camera.width})")
    on = mask == on_value
    if not np.all(on | (mask == 0)):
        raise InputFileError(path, f"mask values must be 0 or {on_value}")
    return on


def _load_npz(path: Path, what: str) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise InputFileError(path, f"{what} missing")
    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise ValueError("not an .npz archive")
        with data:
            return {key: data[key] for key in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
        raise InputFileError(path, f"{what} unreadable ({error})") from None


def _array(data: dict[str, np.ndarray], key: str, path: Path, shape: tuple[int | None, ...] | None) -> np.ndarray:
    """data[key] as float64, checked for presence, shape (None = any size on that axis) and finiteness."""
    if key not in data:
        raise InputFileError(path, f"key '{key}' missing")
    value = data[key]
    if shape is not None and (
        value.ndim != len(shape) or any(want is not None and got != want for got, want in zip(value.shape, shape))
    ):
        wanted = "(" + ", ".join("N" if want is None else str(want) for want in shape) + ")"
        raise InputFileError(path, f"'{key}' has shape {value.shape}, expected {wanted}")
    if not (np.issubdtype(value.dtype, np.number) or value.dtype == np.bool_):
        raise InputFileError(path, f"'{key}' is not numeric (dtype {value.dtype})")
    value = value.astype(np.float64)
    if not np.all(np.isfinite(value)):
        raise InputFileError(path, f"'{key}' holds non-finite values")
    return value


# ----------------------------------------------------------------------------------------------- helpers


def _parallel_map(function: Callable[[_T], _R], items: Iterable[_T]) -> list[_R]:
    """function over items on a thread pool (PNG codecs and numpy release the GIL); re-raises the first error."""
    items = list(items)
    workers = max(1, min(_MAX_THREADS, os.cpu_count() or 1, len(items)))
    if workers == 1:
        return [function(item) for item in items]
    pool = ThreadPoolExecutor(max_workers=workers)
    try:
        return list(pool.map(function, items))
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _as_numpy(array: np.ndarray | torch.Tensor) -> np.ndarray:
    return array.detach().cpu().numpy() if isinstance(array, torch.Tensor) else np.asarray(array)


def check_dataset_output(root: Path) -> None:
    """Refuse (one line) a `root` that `write_people_snapshot` may not replace: anything but a missing path, an
    empty folder or a previous dataset (a folder with cameras.npz)."""
    replaceable = root.is_dir() and ((root / "cameras.npz").is_file() or not any(root.iterdir()))
    if root.exists() and not replaceable:
        raise InputFileError(root, "exists and is not a People-Snapshot dataset; refusing to replace it")


def _move_into_place(staging: Path, root: Path) -> None:
    """Rename the finished `staging` folder onto `root`, moving any previous dataset aside first."""
    if not root.exists():
        os.replace(staging, root)
        return
    previous = Path(tempfile.mkdtemp(prefix=f".{root.name}.", suffix=".old", dir=root.parent))
    os.replace(root, previous / root.name)
    try:
        os.replace(staging, root)
    except BaseException:
        os.replace(previous / root.name, root)
        raise
    finally:
        shutil.rmtree(previous, ignore_errors=True)


@dataclass(frozen=True)
class VideoFingerprint:
    """What tells a video folder from another: its frame count (images/image_%04d.png), the camera's image size
    in pixels, and the SHA-256 over cameras.npz and every frame's image bytes in frame order (None: not hashed)."""

    frames: int
    width: int
    height: int
    sha256: str | None = None


def video_fingerprint(root: Path, content: bool = True) -> VideoFingerprint:
    """The fingerprint of the People-Snapshot folder `root`; `content` False leaves out the hash (no image is read)."""
    root = Path(root)
    frames = _available_frames(root / "images")
    camera = read_dataset_camera(root)
    digest = None
    if content:
        sha = hashlib.sha256((root / "cameras.npz").read_bytes())
        for frame in frames:
            sha.update((root / "images" / f"image_{frame:04d}.png").read_bytes())
        digest = sha.hexdigest()
    return VideoFingerprint(len(frames), camera.width, camera.height, digest)

