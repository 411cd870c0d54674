"""People-Snapshot loader and writer, checked against datasets written by hand with numpy / cv2."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

from avatarperfect_cli.datasets import FrameRange, VideoDataset, load_people_snapshot, write_people_snapshot
from avatarperfect_cli.datasets import people_snapshot
from avatarperfect_cli.errors import InputFileError
from avatarperfect_cli.render.camera import Camera

HEIGHT, WIDTH, FRAMES = 6, 8, 5


@dataclass
class Source:
    """What a test dataset holds, in the file conventions (float64 poses, uint8 RGB images)."""

    root: Path
    images: np.ndarray  # (T, H, W, 3) uint8
    masks: np.ndarray  # (T, H, W) bool
    thetas: np.ndarray  # (T, 72)
    transl: np.ndarray  # (T, 3)
    betas: np.ndarray  # (10,)
    K: np.ndarray  # (3, 3)
    extrinsic: np.ndarray  # (4, 4)


def random_source(root: Path, seed: int = 0, frames: int = FRAMES) -> Source:
    rng = np.random.default_rng(seed)
    angle = 0.3
    rotation = np.array([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]])
    extrinsic = np.eye(4)
    extrinsic[:3, :3] = rotation
    extrinsic[:3, 3] = [0.1, -0.2, 3.0]
    return Source(
        root=root,
        images=rng.integers(0, 256, (frames, HEIGHT, WIDTH, 3), dtype=np.uint8),
        masks=rng.random((frames, HEIGHT, WIDTH)) < 0.5,
        thetas=rng.normal(0, 0.3, (frames, 72)),
        transl=rng.normal(0, 1, (frames, 3)),
        betas=rng.normal(0, 1, 10),
        K=np.array([[10.0, 0.0, 4.2], [0.0, 11.0, 2.9], [0.0, 0.0, 1.0]]),
        extrinsic=extrinsic,
    )


def write_by_hand(source: Source, mask_format: str = "npy", poses: bool = True) -> Source:
    """The layout written with numpy and cv2 only (independent of write_people_snapshot)."""
    root = source.root
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    np.savez(root / "cameras.npz", intrinsic=source.K, extrinsic=source.extrinsic, height=HEIGHT, width=WIDTH)
    for frame, (image, mask) in enumerate(zip(source.images, source.masks)):
        assert cv2.imwrite(str(root / "images" / f"image_{frame:04d}.png"), image[..., ::-1])
        if mask_format == "npy":
            np.save(root / "masks" / f"mask_{frame:04d}.npy", mask.astype(np.uint8))
        else:
            assert cv2.imwrite(str(root / "masks" / f"mask_{frame:04d}.png"), mask.astype(np.uint8) * 255)
    if poses:
        np.savez(root / "poses.npz", betas=source.betas[None], thetas=source.thetas, transl=source.transl)
    return source


@pytest.fixture
def source(tmp_path: Path) -> Source:
    return write_by_hand(random_source(tmp_path / "subject"))


def composited(source: Source, frames: np.ndarray) -> np.ndarray:
    """(T, H, W, 3) float64 reference: image where the mask is set, white elsewhere."""
    images = source.images[frames].astype(np.float64) / 255
    return np.where(source.masks[frames][..., None], images, 1.0)


def assert_matches(data: VideoDataset, source: Source, frames: np.ndarray, pose_rows: np.ndarray) -> None:
    assert data.images.dtype == torch.float32 and data.masks.dtype == torch.bool
    np.testing.assert_array_equal(data.frame_ids.numpy(), frames)
    np.testing.assert_allclose(data.images.numpy(), composited(source, frames), atol=1e-6)
    np.testing.assert_array_equal(data.masks.numpy(), source.masks[frames])
    np.testing.assert_allclose(data.body_pose.numpy(), source.thetas[pose_rows].reshape(-1, 24, 3), atol=1e-6)
    np.testing.assert_allclose(data.transl.numpy(), source.transl[pose_rows], atol=1e-6)
    np.testing.assert_allclose(data.betas.numpy(), source.betas, atol=1e-6)
    np.testing.assert_allclose(data.camera.K.numpy(), source.K, atol=1e-6)
    np.testing.assert_allclose(data.camera.world_to_camera.numpy(), source.extrinsic, atol=1e-6)
    assert (data.camera.width, data.camera.height) == (WIDTH, HEIGHT)
    assert len(data) == len(frames)


def rewrite_npz(path: Path, **changes: object) -> None:
    """Rewrite an .npz with keys replaced (value None removes the key)."""
    with np.load(path) as data:
        contents = {key: data[key] for key in data.files}
    contents.update(changes)
    np.savez(path, **{key: value for key, value in contents.items() if value is not None})


def expect_error(path: Path, **load_args: object) -> InputFileError:
    """Load and expect an InputFileError that names `path` on one line."""
    with pytest.raises(InputFileError) as caught:
        load_people_snapshot(path_root(path), **load_args)
    message = str(caught.value)
    assert str(path) in message and "\n" not in message
    assert Path(caught.value.path) == path
    return caught.value


def path_root(path: Path) -> Path:
    """The dataset root ("subject" folder) a test file lies in."""
    return next(parent for parent in [path, *path.parents] if parent.name == "subject")


# ------------------------------------------------------------------------------------------- layouts


def test_hand_written_dataset_loads_composited_on_white(source: Source) -> None:
    all_frames = np.arange(FRAMES)
    data = load_people_snapshot(source.root)
    assert_matches(data, source, all_frames, all_frames)
    assert data.subject is None
    # Compositing: subject pixels keep the image colour, background pixels are exactly white.
    background = ~source.masks
    assert np.all(data.images.numpy()[background] == 1.0)
    assert data.masks.sum() > 0 and background.sum() > 0


def test_png_masks(tmp_path: Path) -> None:
    source = write_by_hand(random_source(tmp_path / "subject"), mask_format="png")
    data = load_people_snapshot(source.root)
    assert_matches(data, source, np.arange(FRAMES), np.arange(FRAMES))


def test_poses_optimized_with_global_orient_and_body_pose_is_preferred(source: Source) -> None:
    refined = source.thetas + 0.5
    np.savez(
        source.root / "poses_optimized.npz",
        betas=source.betas,
        global_orient=refined[:, :3],
        body_pose=refined[:, 3:],
        transl=source.transl,
    )
    data = load_people_snapshot(source.root, frames=FrameRange(1, 3))
    np.testing.assert_allclose(data.body_pose.numpy(), refined[1:4].reshape(-1, 24, 3), atol=1e-6)
    explicit = load_people_snapshot(source.root, frames=FrameRange(1, 3), pose_source="poses.npz")
    np.testing.assert_allclose(explicit.body_pose.numpy(), source.thetas[1:4].reshape(-1, 24, 3), atol=1e-6)


def test_split_file_rows_follow_the_selected_frames_in_order(source: Source) -> None:
    (source.root / "poses").mkdir()
    # The split's own pose rows: one per selected frame (0, 2, 4), distinct from poses.npz.
    split_thetas = source.thetas[[0, 2, 4]] - 0.25
    np.savez(
        source.root / "poses" / "anim_nerf_train.npz",
        betas=source.betas[None],
        global_orient=split_thetas[:, :3],
        body_pose=split_thetas[:, 3:],
        transl=source.transl[[0, 2, 4]] * 2,
    )
    data = load_people_snapshot(source.root, frames=FrameRange(0, 4, 2), split="train")
    np.testing.assert_array_equal(data.frame_ids.numpy(), [0, 2, 4])
    np.testing.assert_allclose(data.body_pose.numpy(), split_thetas.reshape(-1, 24, 3), atol=1e-6)
    np.testing.assert_allclose(data.transl.numpy(), source.transl[[0, 2, 4]] * 2, atol=1e-6)
    np.testing.assert_allclose(data.images.numpy(), composited(source, np.array([0, 2, 4])), atol=1e-6)


def test_split_file_with_a_different_row_count_is_an_error(source: Source) -> None:
    (source.root / "poses").mkdir()
    split_path = source.root / "poses" / "anim_nerf_test.npz"
    np.savez(split_path, betas=source.betas, thetas=source.thetas[:3], transl=source.transl[:3])
    error = expect_error(split_path, frames=FrameRange(0, 4, 1), split="test")
    assert "3 pose rows for 5 selected frames" in error.problem


def test_missing_split_file_falls_back_to_poses_npz(source: Source) -> None:
    data = load_people_snapshot(source.root, frames=FrameRange(2, 4), split="val")
    np.testing.assert_allclose(data.body_pose.numpy(), source.thetas[2:].reshape(-1, 24, 3), atol=1e-6)


def test_frame_range_indexes_poses_by_frame_number(source: Source) -> None:
    frames = np.array([1, 3])
    data = load_people_snapshot(source.root, frames=FrameRange(1, 4, 2))
    assert_matches(data, source, frames, frames)


def test_loading_every_frame_keeps_gaps_in_frame_numbers(source: Source) -> None:
    (source.root / "images" / "image_0002.png").unlink()
    (source.root / "images" / "notes.png").write_bytes(b"ignored: not a frame name")
    frames = np.array([0, 1, 3, 4])
    assert_matches(load_people_snapshot(source.root), source, frames, frames)


def test_subject_json_is_returned(source: Source) -> None:
    subject = {"body_model": "anny", "phenotype": {"gender": 0.3, "height": 0.6}}
    (source.root / "subject.json").write_text(json.dumps(subject))
    assert load_people_snapshot(source.root).subject == subject


@pytest.mark.parametrize("downscale", [2, 3])
def test_downscale_averages_areas_and_scales_intrinsics(source: Source, downscale: int) -> None:
    data = load_people_snapshot(source.root, downscale=downscale)
    height, width = round(HEIGHT / downscale), round(WIDTH / downscale)
    assert data.images.shape == (FRAMES, height, width, 3) and data.masks.shape == (FRAMES, height, width)
    assert (data.camera.width, data.camera.height) == (width, height)
    # Pixel centres at +0.5: the rows of K scale with the image size along each axis.
    expected_K = source.K.copy()
    expected_K[0] *= width / WIDTH
    expected_K[1] *= height / HEIGHT
    np.testing.assert_allclose(data.camera.K.numpy(), expected_K, rtol=1e-6)
    np.testing.assert_allclose(data.camera.world_to_camera.numpy(), source.extrinsic, atol=1e-6)
    if WIDTH % downscale == 0 and HEIGHT % downscale == 0:
        factor = downscale
        reference = Camera(torch.tensor(source.K, dtype=torch.float32), torch.eye(4), WIDTH, HEIGHT).scaled(1 / factor)
        np.testing.assert_allclose(data.camera.K.numpy(), reference.K.numpy(), rtol=1e-6)
        blocks = (FRAMES, height, factor, width, factor)
        image_means = composited(source, np.arange(FRAMES)).reshape(*blocks, 3).mean(axis=(2, 4))
        np.testing.assert_allclose(data.images.numpy(), image_means, atol=1e-5)
        mask_means = source.masks.reshape(blocks).mean(axis=(2, 4))
        np.testing.assert_array_equal(data.masks.numpy(), mask_means >= 0.5)


# ------------------------------------------------------------------------------------------- writer


def test_writer_round_trip(tmp_path: Path) -> None:
    source = random_source(tmp_path / "subject")
    camera = Camera(torch.tensor(source.K), torch.tensor(source.extrinsic), WIDTH, HEIGHT)
    subject = {"body_model": "smpl", "betas": source.betas.tolist()}
    write_people_snapshot(
        source.root,
        source.images,
        source.masks,
        torch.tensor(source.thetas).reshape(FRAMES, 24, 3),
        source.transl,
        camera,
        betas=source.betas,
        subject=subject,
    )
    data = load_people_snapshot(source.root)
    assert_matches(data, source, np.arange(FRAMES), np.arange(FRAMES))
    assert data.subject == subject
    # The files themselves follow the layout (read without the loader).
    mask = np.load(source.root / "masks" / "mask_0003.npy")
    assert mask.dtype == np.uint8 and np.array_equal(mask, source.masks[3])
    np.testing.assert_array_equal(np.asarray(Image.open(source.root / "images" / "image_0004.png")), source.images[4])
    with np.load(source.root / "poses.npz") as poses:
        assert poses["thetas"].shape == (FRAMES, 72) and poses["betas"].shape == (10,)
    with np.load(source.root / "cameras.npz") as cameras:
        assert int(cameras["height"]) == HEIGHT and int(cameras["width"]) == WIDTH


def test_writer_defaults_betas_to_zero_and_pngs_are_deterministic(tmp_path: Path) -> None:
    source = random_source(tmp_path)
    camera = Camera(torch.tensor(source.K), torch.tensor(source.extrinsic), WIDTH, HEIGHT)
    poses = source.thetas.reshape(FRAMES, 24, 3)
    for name in ("first", "second"):
        write_people_snapshot(tmp_path / name, source.images, source.masks, poses, source.transl, camera)
    for frame in range(FRAMES):
        png = f"images/image_{frame:04d}.png"
        assert (tmp_path / "first" / png).read_bytes() == (tmp_path / "second" / png).read_bytes()
    assert np.all(load_people_snapshot(tmp_path / "first").betas.numpy() == 0)



def test_writer_takes_a_list_of_frames_as_it_takes_their_stack(tmp_path: Path) -> None:
    """`prepare` hands over its frames as a list, so that the video is not held twice: the same files, and
    a frame of the wrong size or type is refused before anything is written."""
    source = random_source(tmp_path)
    camera = Camera(torch.tensor(source.K), torch.tensor(source.extrinsic), WIDTH, HEIGHT)
    poses = source.thetas.reshape(FRAMES, 24, 3)
    write_people_snapshot(tmp_path / "stacked", source.images, source.masks, poses, source.transl, camera)
    write_people_snapshot(tmp_path / "listed", list(source.images), source.masks, poses, source.transl, camera)
    for frame in range(FRAMES):
        png = f"images/image_{frame:04d}.png"
        assert (tmp_path / "stacked" / png).read_bytes() == (tmp_path / "listed" / png).read_bytes()
    for wrong in (source.images[0][:-1], source.images[0].astype(np.float32)):
        frames = [*source.images[:-1], wrong]
        with pytest.raises(ValueError, match=f"image {FRAMES - 1} is"):
            write_people_snapshot(tmp_path / "wrong", frames, source.masks, poses, source.transl, camera)
    assert not (tmp_path / "wrong").exists()

def test_writer_replaces_a_previous_dataset_and_leaves_no_temporaries(tmp_path: Path) -> None:
    old, new = random_source(tmp_path / "subject", seed=1, frames=7), random_source(tmp_path / "subject", seed=2)
    write_by_hand(old)
    camera = Camera(torch.tensor(new.K), torch.tensor(new.extrinsic), WIDTH, HEIGHT)
    write_people_snapshot(new.root, new.images, new.masks, new.thetas.reshape(-1, 24, 3), new.transl, camera)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["subject"]
    data = load_people_snapshot(new.root)
    assert len(data) == FRAMES  # the old frames 5 and 6 are gone
    np.testing.assert_array_equal(data.masks.numpy(), new.masks)


def test_writer_crash_leaves_nothing_behind(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    source = random_source(tmp_path / "subject")
    camera = Camera(torch.tensor(source.K), torch.tensor(source.extrinsic), WIDTH, HEIGHT)

    def crash(*args: object, **kwargs: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(people_snapshot.np, "savez", crash)
    with pytest.raises(OSError, match="disk full"):
        write_people_snapshot(
            source.root, source.images, source.masks, source.thetas.reshape(-1, 24, 3), source.transl, camera
        )
    assert list(tmp_path.iterdir()) == []


def test_writer_refuses_to_replace_a_folder_that_is_not_a_dataset(tmp_path: Path) -> None:
    (tmp_path / "subject").mkdir()
    (tmp_path / "subject" / "thesis.tex").write_text("precious")
    source = random_source(tmp_path / "subject")
    camera = Camera(torch.tensor(source.K), torch.tensor(source.extrinsic), WIDTH, HEIGHT)
    with pytest.raises(InputFileError, match="refusing"):
        write_people_snapshot(
            source.root, source.images, source.masks, source.thetas.reshape(-1, 24, 3), source.transl, camera
        )
    assert (tmp_path / "subject" / "thesis.tex").read_text() == "precious"


# ------------------------------------------------------------------------------------------- errors


def test_error_root_missing(tmp_path: Path) -> None:
    expect_error(tmp_path / "subject")


def test_error_cameras_missing(source: Source) -> None:
    (source.root / "cameras.npz").unlink()
    expect_error(source.root / "cameras.npz")


def test_error_cameras_unreadable(source: Source) -> None:
    (source.root / "cameras.npz").write_bytes(b"PK\x03\x04 not really a zip archive")
    expect_error(source.root / "cameras.npz")


def test_error_cameras_is_a_single_array(source: Source) -> None:
    with open(source.root / "cameras.npz", "wb") as file:
        np.save(file, np.eye(3))
    expect_error(source.root / "cameras.npz")


@pytest.mark.parametrize("key", ["intrinsic", "extrinsic", "height", "width"])
def test_error_cameras_key_missing(source: Source, key: str) -> None:
    rewrite_npz(source.root / "cameras.npz", **{key: None})
    assert key in expect_error(source.root / "cameras.npz").problem


@pytest.mark.parametrize(
    "key, value",
    [("intrinsic", np.eye(3, 4)), ("extrinsic", np.eye(3, 4)), ("height", np.array([6, 6])), ("width", 8.5)],
)
def test_error_cameras_wrong_shape_or_value(source: Source, key: str, value: object) -> None:
    rewrite_npz(source.root / "cameras.npz", **{key: value})
    assert key in expect_error(source.root / "cameras.npz").problem


def test_error_extrinsic_not_rigid(source: Source) -> None:
    rewrite_npz(source.root / "cameras.npz", extrinsic=np.diag([2.0, 1.0, 1.0, 1.0]))
    assert "rigid" in expect_error(source.root / "cameras.npz").problem


def test_error_cameras_non_finite(source: Source) -> None:
    K = source.K.copy()
    K[0, 0] = np.nan
    rewrite_npz(source.root / "cameras.npz", intrinsic=K)
    assert "non-finite" in expect_error(source.root / "cameras.npz").problem


@pytest.mark.parametrize(
    "index, value, problem",
    [((0, 0), 0.0, "positive focal lengths"), ((1, 1), -11.0, "positive focal lengths"), ((2, 1), 0.3, "last row [0, 0, 1]")],
)
def test_error_intrinsic_values(source: Source, index: tuple[int, int], value: float, problem: str) -> None:
    K = source.K.copy()
    K[index] = value
    rewrite_npz(source.root / "cameras.npz", intrinsic=K)
    assert problem in expect_error(source.root / "cameras.npz").problem


def test_error_image_size_beyond_the_maximum(source: Source) -> None:
    rewrite_npz(source.root / "cameras.npz", width=np.int64(30000), height=np.int64(30000))
    assert "maximum side of 8192 px" in expect_error(source.root / "cameras.npz").problem


def test_sixteen_bit_images_keep_their_high_byte(source: Source) -> None:
    """As OpenCV's IMREAD_COLOR does: a 16-bit gray frame v reads as v >> 8 in each channel."""
    gray = np.random.default_rng(3).integers(0, 65536, (HEIGHT, WIDTH), dtype=np.uint16)
    assert cv2.imwrite(str(source.root / "images" / "image_0002.png"), gray)
    data = load_people_snapshot(source.root, FrameRange(2, 2))
    expected = np.where(source.masks[2], (gray >> 8).astype(np.float64) / 255, 1.0)
    np.testing.assert_allclose(data.images[0].numpy(), np.repeat(expected[:, :, None], 3, axis=2), atol=1e-6)


@pytest.mark.parametrize("damage", ["truncated", "bad checksum"])
def test_damaged_png_is_reported_once_and_nothing_is_printed(source: Source, capfd: pytest.CaptureFixture, damage: str) -> None:
    path = source.root / "images" / "image_0003.png"
    data = bytearray(path.read_bytes())
    if damage == "truncated":
        data = data[: len(data) // 2]
    else:
        data[data.index(b"IDAT") + 6] ^= 0xFF  # inside the compressed pixels: the chunk's CRC no longer matches
    path.write_bytes(bytes(data))
    assert "unreadable" in expect_error(path).problem
    captured = capfd.readouterr()
    assert captured.err == "" and captured.out == ""


def test_error_no_images(source: Source) -> None:
    for path in (source.root / "images").iterdir():
        path.unlink()
    expect_error(source.root / "images")


def test_error_images_folder_missing(source: Source) -> None:
    for path in (source.root / "images").iterdir():
        path.unlink()
    (source.root / "images").rmdir()
    expect_error(source.root / "images")


def test_error_image_unreadable(source: Source) -> None:
    (source.root / "images" / "image_0002.png").write_bytes(b"\x89PNG broken")
    assert "unreadable" in expect_error(source.root / "images" / "image_0002.png").problem


def test_error_image_size_differs_from_cameras(source: Source) -> None:
    cv2.imwrite(str(source.root / "images" / "image_0001.png"), np.zeros((HEIGHT, WIDTH + 1, 3), np.uint8))
    assert "cameras.npz" in expect_error(source.root / "images" / "image_0001.png").problem


def test_error_mask_missing(source: Source) -> None:
    (source.root / "masks" / "mask_0003.npy").unlink()
    assert "missing" in expect_error(source.root / "masks" / "mask_0003.npy").problem


def test_error_mask_wrong_shape(source: Source) -> None:
    np.save(source.root / "masks" / "mask_0000.npy", np.ones((HEIGHT, WIDTH, 1), np.uint8))
    assert "shape" in expect_error(source.root / "masks" / "mask_0000.npy").problem


def test_error_npy_mask_values(source: Source) -> None:
    np.save(source.root / "masks" / "mask_0004.npy", np.full((HEIGHT, WIDTH), 255, np.uint8))
    assert "0 or 1" in expect_error(source.root / "masks" / "mask_0004.npy").problem


def test_error_png_mask_values(tmp_path: Path) -> None:
    source = write_by_hand(random_source(tmp_path / "subject"), mask_format="png")
    cv2.imwrite(str(source.root / "masks" / "mask_0002.png"), np.full((HEIGHT, WIDTH), 128, np.uint8))
    assert "0 or 255" in expect_error(source.root / "masks" / "mask_0002.png").problem


def test_error_mask_unreadable(source: Source) -> None:
    (source.root / "masks" / "mask_0001.npy").write_bytes(b"garbage")
    expect_error(source.root / "masks" / "mask_0001.npy")


def test_error_pose_file_missing(tmp_path: Path) -> None:
    source = write_by_hand(random_source(tmp_path / "subject"), poses=False)
    assert "missing" in expect_error(source.root / "poses.npz").problem


def test_error_explicit_pose_source_missing(source: Source) -> None:
    expect_error(source.root / "poses" / "anim_nerf_val.npz", pose_source="poses/anim_nerf_val.npz")


@pytest.mark.parametrize(
    "changes, key",
    [
        ({"thetas": np.zeros((FRAMES, 69))}, "thetas"),
        ({"transl": np.zeros((FRAMES, 2))}, "transl"),
        ({"transl": np.zeros((FRAMES - 1, 3))}, "transl"),
        ({"betas": np.zeros((2, 10))}, "betas"),
        ({"betas": None}, "betas"),
        ({"thetas": None}, "thetas"),
    ],
)
def test_error_poses_wrong_shape_or_missing(source: Source, changes: dict, key: str) -> None:
    rewrite_npz(source.root / "poses.npz", **changes)
    assert key in expect_error(source.root / "poses.npz").problem


def test_error_body_pose_wrong_shape(source: Source) -> None:
    path = source.root / "poses_optimized.npz"
    np.savez(path, betas=source.betas, global_orient=np.zeros((FRAMES, 3)), body_pose=np.zeros((FRAMES, 23, 3)))
    assert "body_pose" in expect_error(path).problem


def test_error_fewer_pose_rows_than_frames(source: Source) -> None:
    rewrite_npz(source.root / "poses.npz", thetas=source.thetas[:3], transl=source.transl[:3])
    load_people_snapshot(source.root, frames=FrameRange(0, 2))  # frames 0..2 have poses
    assert "frame 4" in expect_error(source.root / "poses.npz", frames=FrameRange(2, 4)).problem


@pytest.mark.parametrize("key", ["thetas", "transl", "betas"])
def test_error_poses_non_finite(source: Source, key: str) -> None:
    with np.load(source.root / "poses.npz") as poses:
        value = poses[key].copy()
    value.reshape(-1)[-1] = np.inf
    rewrite_npz(source.root / "poses.npz", **{key: value})
    assert "non-finite" in expect_error(source.root / "poses.npz").problem


def test_error_frame_range_selects_nothing(source: Source) -> None:
    assert "no frames" in expect_error(source.root / "images", frames=FrameRange(3, 2)).problem


def test_error_frame_range_past_the_last_image(source: Source) -> None:
    assert "last image" in expect_error(source.root / "images", frames=FrameRange(0, 8, 4)).problem


def test_error_frame_range_selects_a_missing_image(source: Source) -> None:
    (source.root / "images" / "image_0002.png").unlink()
    expect_error(source.root / "images" / "image_0002.png", frames=FrameRange(0, 4, 2))


def test_error_subject_json_malformed(source: Source) -> None:
    (source.root / "subject.json").write_text('{"body_model": "anny",')
    expect_error(source.root / "subject.json")


def test_invalid_arguments_are_programming_errors(source: Source) -> None:
    with pytest.raises(ValueError):
        FrameRange(0, 4, 0)
    with pytest.raises(ValueError):
        load_people_snapshot(source.root, split="training")
    with pytest.raises(ValueError):
        load_people_snapshot(source.root, downscale=0)


# ------------------------------------------------------------------ split files whose frames are not stored


def write_split(root: Path, split: str, thetas: np.ndarray, transl: np.ndarray, betas: np.ndarray) -> Path:
    """An InstantAvatar split file: betas (1, 10), global_orient (N, 3), body_pose (N, 69), transl (N, 3)."""
    path = root / "poses" / f"anim_nerf_{split}.npz"
    path.parent.mkdir(exist_ok=True)
    np.savez(path, betas=betas[None], global_orient=thetas[:, :3], body_pose=thetas[:, 3:], transl=transl)
    return path


@pytest.fixture
def twelve_frames(tmp_path: Path) -> Source:
    """12 frames and no poses.npz: an InstantAvatar folder keeps its poses in split files only."""
    return write_by_hand(random_source(tmp_path / "subject", frames=12), poses=False)


def test_a_split_with_a_row_per_image_covers_every_image(twelve_frames: Source) -> None:
    source = twelve_frames
    write_split(source.root, "train", source.thetas, source.transl, source.betas)
    data = load_people_snapshot(source.root, split="train")
    assert_matches(data, source, np.arange(12), np.arange(12))
    assert data.pose_file == "poses/anim_nerf_train.npz" and data.notes == ()


def test_train_and_test_splits_tile_the_video_with_one_step(twelve_frames: Source) -> None:
    """4 train rows + 2 test rows for 12 images: step 2, train 0..6, test 8..10; said in one note each."""
    source = twelve_frames
    train_frames, test_frames = np.arange(0, 8, 2), np.array([8, 10])
    write_split(source.root, "train", source.thetas[train_frames], source.transl[train_frames], source.betas)
    write_split(source.root, "test", source.thetas[test_frames], source.transl[test_frames], source.betas)
    for split, frames in (("train", train_frames), ("test", test_frames)):
        data = load_people_snapshot(source.root, split=split)
        assert_matches(data, source, frames, frames)
        (note,) = data.notes
        assert f"anim_nerf_{split}.npz" in note and f"frames {frames[0]}..{frames[-1]} step 2" in note
        assert "does not store which frames" in note and "--frames" in note and "\n" not in note
    val = write_split(source.root, "val", source.thetas[[8]], source.transl[[8]], source.betas)
    assert load_people_snapshot(source.root, split="val").frame_ids.tolist() == [8]  # InstantAvatar: the first test frame
    val.unlink()
    # An explicit range wins over the convention (its row count must match).
    data = load_people_snapshot(source.root, frames=FrameRange(1, 7, 2), split="train")
    assert data.frame_ids.tolist() == [1, 3, 5, 7] and data.notes == ()


def test_a_public_instantavatar_subject_uses_its_config(tmp_path: Path) -> None:
    """female-4-casual tests on 335..523 step 4, one frame before the tiling convention's 336: the folder's
    name and the split's row count select the config. Only the image names matter without images."""
    root = tmp_path / "female-4-casual"
    (root / "images").mkdir(parents=True)
    for frame in range(524):
        (root / "images" / f"image_{frame:04d}.png").touch()
    np.savez(root / "cameras.npz", intrinsic=np.diag([500.0, 500.0, 1.0]), extrinsic=np.eye(4), height=540, width=540)
    rng = np.random.default_rng(3)
    for split, rows in (("train", 84), ("test", 48)):
        write_split(root, split, rng.normal(size=(rows, 72)), rng.normal(size=(rows, 3)), np.zeros(10))
    test = load_people_snapshot(root, split="test", with_images=False)
    assert test.frame_ids.tolist() == list(range(335, 524, 4))
    assert "InstantAvatar's female-4-casual config" in test.notes[0]
    assert load_people_snapshot(root, split="train", with_images=False).frame_ids.tolist() == list(range(0, 336, 4))
    renamed = root.rename(tmp_path / "my-subject")  # the tiling convention would run past the last image
    with pytest.raises(InputFileError, match="anim_nerf_test.npz: holds 48 pose rows for 524 images.*--frames"):
        load_people_snapshot(renamed, split="test", with_images=False)


def test_a_split_that_fits_no_frames_is_one_line_naming_it(twelve_frames: Source) -> None:
    source = twelve_frames
    too_many = write_split(source.root, "train", np.zeros((13, 72)), np.zeros((13, 3)), source.betas)
    assert "13 pose rows, more than the 12 images" in expect_error(too_many, split="train").problem
    write_split(source.root, "train", np.zeros((5, 72)), np.zeros((5, 3)), source.betas)
    test = write_split(source.root, "test", np.zeros((3, 72)), np.zeros((3, 3)), source.betas)  # step 2: test 10..14
    assert "give them with --frames" in expect_error(test, split="test").problem


def test_wrong_betas_in_a_split_file_are_one_line_naming_it(twelve_frames: Source) -> None:
    source = twelve_frames
    path = write_split(source.root, "train", source.thetas, source.transl, source.betas)
    rewrite_npz(path, betas=np.zeros((1, 16)))
    assert "'betas' has shape (1, 16)" in expect_error(path, split="train").problem


def test_a_folder_with_both_kinds_of_pose_file_says_which_it_read(source: Source) -> None:
    split_thetas = source.thetas - 0.1
    write_split(source.root, "train", split_thetas, source.transl, source.betas)
    data = load_people_snapshot(source.root, split="train")
    np.testing.assert_allclose(data.body_pose.numpy(), split_thetas.reshape(-1, 24, 3), atol=1e-6)
    (note,) = data.notes
    assert "poses from poses/anim_nerf_train.npz" in note and "also there: poses.npz" in note and "--poses" in note
    explicit = load_people_snapshot(source.root, split="train", pose_source="poses.npz")
    assert explicit.pose_file == "poses.npz" and explicit.notes == ()
    np.testing.assert_allclose(explicit.body_pose.numpy(), source.thetas.reshape(-1, 24, 3), atol=1e-6)


def test_only_split_files_and_no_split_asks_for_one(twelve_frames: Source) -> None:
    write_split(twelve_frames.root, "train", twelve_frames.thetas, twelve_frames.transl, twelve_frames.betas)
    error = expect_error(twelve_frames.root / "poses.npz")
    assert "anim_nerf_train.npz" in error.problem and "--poses" in error.problem
