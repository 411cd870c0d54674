"""The damaged-input corpus: valid inputs built in code, and cases that each damage one file of them.

A `Case` builds its input files under a folder, returns the damaged file, and gives the command line that
reads it; the harness (test_damaged_inputs.py) runs the real CLI and checks the answer. An input class is
one `InputClass` entry in INPUT_CLASSES: the valid files, the command that reads them, and the damages.
A future class (e.g. the edits' PNGs for apply-edit) joins by adding its entry there.

Outputs are named inside the case's folder, so the harness can check that nothing appeared there.
"""

from __future__ import annotations

import json
import math
import shutil
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.datasets import write_people_snapshot
from avatarperfect_cli.gaussians import Gaussians, rgb_to_sh
from avatarperfect_cli.io import write_camera, write_gaussians, write_image, write_pose
from avatarperfect_cli.io.camera_json import camera_to_json
from avatarperfect_cli.io.motion import write_motion
from avatarperfect_cli.io.pose_json import PoseFile
from avatarperfect_cli.render import Camera, look_at

Damage = Callable[[Path], None]  # rewrites the file (or folder) at the path it is given


@dataclass(frozen=True)
class Case:
    """name: "class/damage"; make_files(root) writes the inputs under `root` and returns the damaged file (or the
    output refused); argv(root) is the command line (after `avatarperfect`) that reads them; names: what the error
    line must quote instead of the damaged file's name (a bad option's value)."""

    name: str
    make_files: Callable[[Path], Path]
    argv: Callable[[Path], list[str]]
    names: str | None = None


@dataclass(frozen=True)
class InputClass:
    """valid(root) writes a complete, valid set of inputs; argv(root) reads them; each damage names the file
    it breaks (relative to root) and how."""

    name: str
    valid: Callable[[Path], None]
    argv: Callable[[Path], list[str]]
    damages: dict[str, tuple[str, Damage]]

    def cases(self) -> list[Case]:
        return [
            Case(f"{self.name}/{label}", _damaged(self.valid, target, damage), self.argv)
            for label, (target, damage) in self.damages.items()
        ]


def _damaged(valid: Callable[[Path], None], target: str, damage: Damage) -> Callable[[Path], Path]:
    def make_files(root: Path) -> Path:
        valid(root)
        damage(root / target)
        return root / target

    return make_files


# ------------------------------------------------------------------------------------------- valid inputs

WIDTH, HEIGHT = 24, 16


def camera() -> Camera:
    """A camera 3 m in front of the origin (on +z), looking at it, +y up."""
    view = look_at(torch.tensor([0.0, 0.0, 3.0]), torch.zeros(3), torch.tensor([0.0, 1.0, 0.0]))
    return Camera(torch.tensor([[30.0, 0.0, WIDTH / 2], [0.0, 30.0, HEIGHT / 2], [0.0, 0.0, 1.0]]), view, WIDTH, HEIGHT)


def gaussians(count: int = 20) -> Gaussians:
    """`count` small red Gaussians around the origin."""
    generator = torch.Generator().manual_seed(0)
    return Gaussians(
        means=(torch.rand(count, 3, generator=generator) - 0.5) * 0.4,
        quats=torch.randn(count, 4, generator=generator),
        log_scales=torch.full((count, 3), -3.0),
        opacity_logits=torch.full((count,), 2.0),
        sh=rgb_to_sh(torch.tensor([1.0, 0.0, 0.0])).expand(count, 1, 3).clone(),
    )


def avatar(count: int = 20) -> Avatar:
    """A tiny skinned avatar: `gaussians` bound to the root joint, rest joints at the origin."""
    g = gaussians(count)
    skin_logits = torch.full((count, 24), -30.0)
    skin_logits[:, 0] = 0.0
    params = {
        "means": g.means,
        "quats": g.quats,
        "log_scales": g.log_scales,
        "opacity_logits": g.opacity_logits,
        "sh_dc": g.sh[:, :1],
        "sh_rest": g.sh[:, 1:],
        "skin_logits": skin_logits,
    }
    return Avatar(params, torch.zeros(24, 3), sh_degree=0)


def write_workspace(root: Path) -> None:
    """A workspace as train-initial leaves it (manifest + avatar/000.ply), written by hand."""
    (root / "avatar").mkdir(parents=True)
    avatar().save(root / "avatar" / "000.ply")
    manifest = {
        "format": "avatarperfect.workspace",
        "version": 1,
        "dataset": str(root / "missing-dataset"),
        "frames": None,
        "downscale": 1,
        "camera": camera_to_json(camera()),
        "body_model": {"name": "test"},
        "reference_pose": {"body_pose": [[0.0] * 3] * 24, "transl": [0.0, 0.0, 0.0]},
        "iteration": 0,
        "history": [{"stage": "train-initial", "avatar": 0}],
    }
    (root / "workspace.json").write_text(json.dumps(manifest, indent=2))


def write_dataset(root: Path, frames: int = 2) -> None:
    """A People-Snapshot folder: `frames` random frames of WIDTH x HEIGHT, poses.npz with zero poses."""
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (frames, HEIGHT, WIDTH, 3), dtype=np.uint8)
    masks = rng.random((frames, HEIGHT, WIDTH)) < 0.5
    write_people_snapshot(root, images, masks, np.zeros((frames, 24, 3)), np.zeros((frames, 3)), camera())


def write_motion_file(path: Path, frames: int = 3) -> None:
    body_pose = torch.zeros(frames, 24, 3)
    body_pose[:, 16, 2] = torch.linspace(-1.0, 1.0, frames)
    write_motion(path, body_pose, torch.zeros(frames, 3))


def _static_inputs(root: Path) -> None:
    write_gaussians(root / "scene.ply", gaussians())
    write_camera(root / "camera.json", camera())


def _avatar_inputs(root: Path) -> None:
    avatar().save(root / "avatar.ply")
    write_camera(root / "camera.json", camera())
    write_pose(root / "pose.json", PoseFile(torch.zeros(24, 3), torch.zeros(3), camera()))
    write_motion_file(root / "motion.npz")


# ------------------------------------------------------------------------------------------------ damages


def write_bytes(data: bytes) -> Damage:
    return lambda path: path.write_bytes(data)


def truncate(fraction: float) -> Damage:
    def damage(path: Path) -> None:
        data = path.read_bytes()
        path.write_bytes(data[: int(len(data) * fraction)])

    return damage


def replace_bytes(old: bytes, new: bytes) -> Damage:
    def damage(path: Path) -> None:
        data = path.read_bytes()
        assert old in data, f"{path} does not hold {old!r}"
        path.write_bytes(data.replace(old, new, 1))

    return damage


def append_bytes(data: bytes) -> Damage:
    return lambda path: path.write_bytes(path.read_bytes() + data)


def make_folder(path: Path) -> None:
    path.unlink()
    path.mkdir()
    (path / "inside.txt").write_text("a folder where a file belongs")


def remove(path: Path) -> None:
    path.unlink()


def edit_json(change: Callable[[dict], None]) -> Damage:
    """Rewrite a JSON object file after `change` mutated it."""

    def damage(path: Path) -> None:
        data = json.loads(path.read_text())
        change(data)
        path.write_text(json.dumps(data))

    return damage


def set_key(*keys: str, value: object) -> Callable[[dict], None]:
    """Set data[k1][k2]... = value; the value DELETE removes the key."""

    def change(data: dict) -> None:
        for key in keys[:-1]:
            data = data[key]
        if value is DELETE:
            del data[keys[-1]]
        else:
            data[keys[-1]] = value

    return change


DELETE = object()


def set_entry(key_path: tuple[str, ...], index: tuple[int, ...], value: float) -> Callable[[dict], None]:
    """Set one matrix entry data[k...][i][j] = value."""

    def change(data: dict) -> None:
        for key in key_path:
            data = data[key]
        for i in index[:-1]:
            data = data[i]
        data[index[-1]] = value

    return change


def rewrite_npz(**changes: object) -> Damage:
    """Rewrite an .npz with keys replaced (DELETE removes one); values are saved as given (pickle refused on load)."""

    def damage(path: Path) -> None:
        with np.load(path) as data:
            contents = {key: data[key] for key in data.files}
        for key, value in changes.items():
            if value is DELETE:
                del contents[key]
            else:
                contents[key] = value
        with open(path, "wb") as handle:
            np.savez(handle, **contents)

    return damage


def edit_npz_array(key: str, change: Callable[[np.ndarray], np.ndarray]) -> Damage:
    def damage(path: Path) -> None:
        with np.load(path) as data:
            value = data[key]
        rewrite_npz(**{key: change(value.copy())})(path)

    return damage


def set_array_entry(index: tuple[int, ...], value: float) -> Callable[[np.ndarray], np.ndarray]:
    def change(array: np.ndarray) -> np.ndarray:
        array = array.astype(np.float64)
        array[index] = value
        return array

    return change


def save_npy(value: np.ndarray) -> Damage:
    """Replace the file by a single .npy array (keeping the file name)."""

    def damage(path: Path) -> None:
        with open(path, "wb") as handle:
            np.save(handle, value)

    return damage


def huge_npz_member(key: str) -> Damage:
    """Replace `key` by an .npy member whose header declares 10^12 rows but holds none."""

    def damage(path: Path) -> None:
        with np.load(path) as data:
            contents = {k: data[k] for k in data.files if k != key}
        header = {"descr": "<f4", "fortran_order": False, "shape": (10**12, 72)}
        member = np.lib.format.magic(1, 0) + _npy_header(header)
        with open(path, "wb") as handle:
            np.savez(handle, **contents)
        with zipfile.ZipFile(path, "a") as archive:
            archive.writestr(f"{key}.npy", member)

    return damage


def _npy_header(header: dict) -> bytes:
    text = repr(header).encode("latin1")
    padding = 64 - (10 + len(text) + 1) % 64
    text += b" " * padding + b"\n"
    return len(text).to_bytes(2, "little") + text


def _rotation_scaled() -> list[list[float]]:
    view = camera().world_to_camera.clone()
    view[0, :3] *= 1.5
    return view.tolist()


def _reflection() -> list[list[float]]:
    view = camera().world_to_camera.clone()
    view[0, :3] *= -1
    return view.tolist()


# ---------------------------------------------------------------------------------------- damage catalogues

COMMON_FILE_DAMAGES: dict[str, Damage] = {
    "empty": write_bytes(b""),
    "binary garbage": write_bytes(bytes(range(256)) * 4),
    "folder": make_folder,
    "missing": remove,
}


def camera_damages(keys: tuple[str, ...] = ()) -> dict[str, Damage]:
    """Damages of a camera JSON object at data[keys...] (the whole file when keys is empty)."""
    at = keys
    return {
        "K missing": edit_json(set_key(*at, "K", value=DELETE)),
        "K 2x3": edit_json(set_key(*at, "K", value=[[30.0, 0.0, 12.0], [0.0, 30.0, 8.0]])),
        "K string entry": edit_json(set_entry((*at, "K"), (0, 2), "12")),  # type: ignore[arg-type]
        "K NaN": edit_json(set_entry((*at, "K"), (0, 0), math.nan)),
        "K Infinity": edit_json(set_entry((*at, "K"), (1, 1), math.inf)),
        "fx zero": edit_json(set_entry((*at, "K"), (0, 0), 0.0)),
        "fy negative": edit_json(set_entry((*at, "K"), (1, 1), -30.0)),
        "K beyond float32": edit_json(set_entry((*at, "K"), (0, 2), 1e39)),
        "not a rotation": edit_json(set_key(*at, "world_to_camera", value=_rotation_scaled())),
        "reflection": edit_json(set_key(*at, "world_to_camera", value=_reflection())),
        "view last row": edit_json(set_entry((*at, "world_to_camera"), (3, 2), 1.0)),
        "width zero": edit_json(set_key(*at, "width", value=0)),
        "height fractional": edit_json(set_key(*at, "height", value=15.5)),
        "width string": edit_json(set_key(*at, "width", value="24")),
        "huge size": edit_json(set_key(*at, "width", value=30000)),
    }


def _ply_damages() -> dict[str, tuple[str, Damage]]:
    damages: dict[str, Damage] = {
        **COMMON_FILE_DAMAGES,
        "text": write_bytes(b"hello, this is not a PLY\n"),
        "truncated header": truncate(0.05),
        "truncated body": truncate(0.8),
        "fewer vertices declared": replace_bytes(b"element vertex 20", b"element vertex 15"),
        "trailing garbage": append_bytes(b"\x01" * 40),
        "huge vertex count": replace_bytes(b"element vertex 20", b"element vertex 999999999999"),
        "missing opacity": replace_bytes(b"property float opacity", b"property float opacitx"),
        "integer property": replace_bytes(b"property float x", b"property int x"),
        "f_rest count": replace_bytes(b"property float f_dc_2", b"property float f_rest_0"),
        "bad comment JSON": replace_bytes(b"comment avatarperfect {", b"comment avatarperfect {{"),
        "newer version": replace_bytes(b'{"version":1', b'{"version":9'),
        "NaN means": _ply_value("x", math.nan),
        "Inf scale": _ply_value("scale_0", math.inf),
    }
    return {label: ("scene.ply", damage) for label, damage in damages.items()}


def _ply_value(name: str, value: float) -> Damage:
    """Set property `name` of vertex 3 in a binary float32 PLY."""

    def damage(path: Path) -> None:
        data = bytearray(path.read_bytes())
        header_end = data.index(b"end_header\n") + len(b"end_header\n")
        names = [line.split()[-1] for line in data[:header_end].decode().splitlines() if line.startswith("property")]
        offset = header_end + (3 * len(names) + names.index(name)) * 4
        data[offset : offset + 4] = np.float32(value).tobytes()
        path.write_bytes(bytes(data))

    return damage


def _camera_file_damages() -> dict[str, tuple[str, Damage]]:
    damages: dict[str, Damage] = {
        **COMMON_FILE_DAMAGES,
        "not JSON": write_bytes(b'{"K": [[1, 0'),
        "array": write_bytes(b"[1, 2, 3]"),
        "newer version": edit_json(set_key("version", value=99)),
        **camera_damages(),
    }
    return {label: ("camera.json", damage) for label, damage in damages.items()}


def _pose_damages() -> dict[str, tuple[str, Damage]]:
    damages: dict[str, Damage] = {
        **COMMON_FILE_DAMAGES,
        "not JSON": write_bytes(b'{"body_pose": '),
        "body_pose missing": edit_json(set_key("body_pose", value=DELETE)),
        "body_pose 23 joints": edit_json(set_key("body_pose", value=[[0.0] * 3] * 23)),
        "body_pose NaN": edit_json(set_entry(("body_pose",), (5, 1), math.nan)),
        "transl 2 values": edit_json(set_key("transl", value=[0.0, 0.0])),
        "transl string": edit_json(set_key("transl", value="0 0 0")),
        "camera missing": edit_json(set_key("camera", value=DELETE)),
        "camera a list": edit_json(set_key("camera", value=[1, 2])),
        **{f"camera {label}": damage for label, damage in camera_damages(("camera",)).items()},
    }
    return {label: ("pose.json", damage) for label, damage in damages.items()}


def _motion_damages() -> dict[str, tuple[str, Damage]]:
    damages: dict[str, Damage] = {
        **COMMON_FILE_DAMAGES,
        "text": write_bytes(b"poses,trans\n"),
        "truncated": truncate(0.5),
        "single .npy": save_npy(np.zeros((3, 72), np.float32)),
        "poses strings": rewrite_npz(poses=np.full((3, 72), "0.0")),
        "trans strings": rewrite_npz(trans=np.full((3, 3), "x")),
        "poses objects": rewrite_npz(poses=np.array([None] * 3, dtype=object)),
        "poses complex": rewrite_npz(poses=np.zeros((3, 72), np.complex64)),
        "poses missing": rewrite_npz(poses=DELETE),
        "trans missing": rewrite_npz(trans=DELETE),
        "poses 60 wide": rewrite_npz(poses=np.zeros((3, 60), np.float32)),
        "poses 69 wide (no global orientation)": rewrite_npz(poses=np.zeros((3, 69), np.float32)),
        "poses 156 wide (SMPL-H, AMASS)": rewrite_npz(poses=np.zeros((3, 156), np.float32)),
        "poses 1-D": rewrite_npz(poses=np.zeros(72, np.float32)),
        "zero frames": rewrite_npz(poses=np.zeros((0, 72), np.float32), trans=np.zeros((0, 3), np.float32)),
        "trans rows": rewrite_npz(trans=np.zeros((2, 3), np.float32)),
        "poses NaN": edit_npz_array("poses", set_array_entry((1, 7), math.nan)),
        "trans Inf": edit_npz_array("trans", set_array_entry((2, 0), math.inf)),
        "huge poses": huge_npz_member("poses"),
    }
    return {label: ("motion.npz", damage) for label, damage in damages.items()}


def _dataset_damages() -> dict[str, tuple[str, Damage]]:
    cameras, poses, split = "data/cameras.npz", "data/poses.npz", "data/poses/anim_nerf_train.npz"
    image, mask = "data/images/image_0001.png", "data/masks/mask_0000.npy"
    damages = {f"cameras.npz {label}": (cameras, damage) for label, damage in COMMON_FILE_DAMAGES.items()}
    damages.update(
        {
            "cameras.npz truncated": (cameras, truncate(0.5)),
            "cameras.npz single .npy": (cameras, save_npy(np.eye(3))),
            "cameras.npz fx zero": (cameras, edit_npz_array("intrinsic", set_array_entry((0, 0), 0.0))),
            "cameras.npz fy negative": (cameras, edit_npz_array("intrinsic", set_array_entry((1, 1), -30.0))),
            "cameras.npz K NaN": (cameras, edit_npz_array("intrinsic", set_array_entry((0, 2), math.nan))),
            "cameras.npz K last row": (cameras, edit_npz_array("intrinsic", set_array_entry((2, 0), 0.5))),
            "cameras.npz not a rotation": (cameras, edit_npz_array("extrinsic", set_array_entry((0, 0), 2.0))),
            "cameras.npz reflection": (cameras, rewrite_npz(extrinsic=np.diag([-1.0, -1.0, -1.0, 1.0]))),
            "cameras.npz extrinsic Inf": (cameras, edit_npz_array("extrinsic", set_array_entry((2, 3), math.inf))),
            "cameras.npz intrinsic missing": (cameras, rewrite_npz(intrinsic=DELETE)),
            "cameras.npz width missing": (cameras, rewrite_npz(width=DELETE)),
            "cameras.npz intrinsic 3x4": (cameras, rewrite_npz(intrinsic=np.eye(3, 4))),
            "cameras.npz intrinsic strings": (cameras, rewrite_npz(intrinsic=np.full((3, 3), "1"))),
            "cameras.npz objects": (cameras, rewrite_npz(intrinsic=np.array([None] * 9, dtype=object))),
            "cameras.npz huge size": (cameras, rewrite_npz(width=np.int64(30000), height=np.int64(30000))),
            "cameras.npz width zero": (cameras, rewrite_npz(width=np.int64(0))),
            "cameras.npz height fractional": (cameras, rewrite_npz(height=np.float64(15.5))),
            "image truncated": (image, truncate(0.5)),
            "image empty": (image, write_bytes(b"")),
            "image text": (image, write_bytes(b"not an image")),
            "image wrong size": (image, _write_png(np.zeros((HEIGHT + 1, WIDTH, 3), np.uint8))),
            "image folder": (image, make_folder),
            "mask missing": (mask, remove),
            "mask truncated": (mask, truncate(0.5)),
            "mask wrong shape": (mask, save_npy(np.zeros((HEIGHT, WIDTH, 1), np.uint8))),
            "mask values": (mask, save_npy(np.full((HEIGHT, WIDTH), 7, np.uint8))),
            "mask strings": (mask, save_npy(np.full((HEIGHT, WIDTH), "1"))),
            "poses.npz missing": (poses, remove),
            "poses.npz empty": (poses, write_bytes(b"")),
            "poses.npz thetas missing": (poses, rewrite_npz(thetas=DELETE)),
            "poses.npz thetas 60 wide": (poses, rewrite_npz(thetas=np.zeros((2, 60)))),
            "poses.npz thetas NaN": (poses, edit_npz_array("thetas", set_array_entry((1, 3), math.nan))),
            "poses.npz thetas strings": (poses, rewrite_npz(thetas=np.full((2, 72), "0"))),
            "poses.npz too few rows": (poses, rewrite_npz(thetas=np.zeros((1, 72)), transl=np.zeros((1, 3)))),
            "poses.npz transl rows": (poses, rewrite_npz(transl=np.zeros((1, 3)))),
            "poses.npz betas shape": (poses, rewrite_npz(betas=np.zeros(7))),
            "poses.npz single .npy": (poses, save_npy(np.zeros((2, 72)))),
            "split file more rows than images": (split, write_split_file(3)),
            "split file betas 16": (split, write_split_file(2, betas=np.zeros((1, 16)))),
            "split file body_pose 72 wide": (split, write_split_file(2, body_pose_width=72)),
        }
    )
    return damages


def write_split_file(rows: int, betas: np.ndarray | None = None, body_pose_width: int = 69) -> Damage:
    """Write an InstantAvatar split file (global_orient, body_pose, transl, betas (1, 10)) at the path."""

    def damage(path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as handle:
            np.savez(
                handle,
                betas=np.zeros((1, 10)) if betas is None else betas,
                global_orient=np.zeros((rows, 3)),
                body_pose=np.zeros((rows, body_pose_width)),
                transl=np.zeros((rows, 3)),
            )

    return damage


def _write_png(pixels: np.ndarray) -> Damage:
    def damage(path: Path) -> None:
        Image.fromarray(pixels).save(path, format="PNG")

    return damage


def _manifest_damages() -> dict[str, tuple[str, Damage]]:
    damages: dict[str, Damage] = {
        "empty": write_bytes(b""),
        "not JSON": write_bytes(b'{"format": "avatarperfect.workspace", '),
        "array": write_bytes(b"[]"),
        "format": edit_json(set_key("format", value="something.else")),
        "iteration missing": edit_json(set_key("iteration", value=DELETE)),
        "iteration string": edit_json(set_key("iteration", value="0")),
        "camera missing": edit_json(set_key("camera", value=DELETE)),
        "camera a string": edit_json(set_key("camera", value="front")),
        "reference_pose missing": edit_json(set_key("reference_pose", value=DELETE)),
        "reference_pose 23 joints": edit_json(set_key("reference_pose", "body_pose", value=[[0.0] * 3] * 23)),
        "reference_pose transl NaN": edit_json(set_entry(("reference_pose", "transl"), (1,), math.nan)),
        "downscale a string": edit_json(set_key("downscale", value="2")),
        "dataset a number": edit_json(set_key("dataset", value=7)),
        "transl_offset a string": edit_json(set_key("transl_offset", value="0 0 0")),
        "history a string": edit_json(set_key("history", value="abc")),
        "history entry a string": edit_json(set_key("history", value=[{"stage": "train-initial", "avatar": 0}, "oops"])),
        "history avatar a string": edit_json(set_key("history", value=[{"stage": "train-initial", "avatar": "0"}])),
        **{f"camera {label}": damage for label, damage in camera_damages(("camera",)).items()},
    }
    return {label: ("ws/workspace.json", damage) for label, damage in damages.items()}


def _workspace_avatar_damages() -> dict[str, tuple[str, Damage]]:
    return {
        "avatar missing": ("ws/avatar/000.ply", remove),
        "avatar truncated": ("ws/avatar/000.ply", truncate(0.7)),
        "avatar without skin weights": ("ws/avatar/000.ply", replace_bytes(b"skin_weights_0", b"skin_weightz_0")),
    }


def _evaluate_damages() -> dict[str, tuple[str, Damage]]:
    """The test video of `evaluate` (same loader as train-initial, plus the size check against the training)."""
    return {
        "test cameras.npz fx zero": ("test/cameras.npz", edit_npz_array("intrinsic", set_array_entry((0, 0), 0.0))),
        "test poses.npz missing": ("test/poses.npz", remove),
        "test split file more rows than images": ("test/poses/anim_nerf_test.npz", write_split_file(4)),
        "test resolution differs": ("test", _resized_dataset(2)),
    }


def _resized_dataset(factor: int) -> Damage:
    """Rewrite the dataset folder at `factor` times the training size (same content otherwise)."""

    def damage(path: Path) -> None:
        rng = np.random.default_rng(1)
        height, width = HEIGHT * factor, WIDTH * factor
        bigger = camera().scaled(factor)
        shutil.rmtree(path)
        images = rng.integers(0, 256, (2, height, width, 3), dtype=np.uint8)
        write_people_snapshot(path, images, np.ones((2, height, width), bool), np.zeros((2, 24, 3)), np.zeros((2, 3)), bigger)

    return damage


def _workspace_and_test(root: Path) -> None:
    write_workspace(root / "ws")
    write_dataset(root / "test")


def _render_static(root: Path) -> list[str]:
    return ["render", str(root / "scene.ply"), "--camera", str(root / "camera.json"), "-o", str(root / "image.png")]


def _workspace_only(root: Path) -> None:
    write_workspace(root / "ws")


def _unpainted(root: Path) -> torch.Tensor:
    """The workspace's avatar in pose.json as apply-edit renders it to compare with a painted image (8-bit, on white)."""
    from avatarperfect_cli.avatar.rendering import render_avatar

    pose = PoseFile(torch.zeros(24, 3), torch.zeros(3), camera())
    with torch.no_grad():
        image = render_avatar(Avatar.load(root / "ws" / "avatar" / "000.ply"), pose.body_pose, pose.transl, pose.camera, torch.ones(3))
    return image.image.clamp(0, 1)


def _edit_inputs(root: Path) -> None:
    """A workspace, a pose JSON and edited.png: the avatar rendered in that pose with a 4x4 blue square painted on."""
    write_workspace(root / "ws")
    write_pose(root / "pose.json", PoseFile(torch.zeros(24, 3), torch.zeros(3), camera()))
    painted = _unpainted(root)
    painted[2:6, 2:6] = torch.tensor([0.0, 0.0, 1.0])
    write_image(root / "edited.png", painted)


def _edit_damages() -> dict[str, tuple[str, Damage]]:
    damages: dict[str, Damage] = {
        **COMMON_FILE_DAMAGES,
        "text": write_bytes(b"not a PNG\n"),
        "truncated": truncate(0.5),
        "header only": truncate(0.1),
        "wrong size": _write_png(np.zeros((HEIGHT + 1, WIDTH, 3), np.uint8)),
        "blank (nothing painted)": lambda path: write_image(path, _unpainted(path.parent)),
    }
    return {label: ("edited.png", damage) for label, damage in damages.items()}


INPUT_CLASSES: list[InputClass] = [
    InputClass(
        "ply",
        _static_inputs,
        _render_static,
        _ply_damages(),
    ),
    InputClass(
        "camera-json",
        _static_inputs,
        _render_static,
        _camera_file_damages(),
    ),
    InputClass(
        "pose-json",
        _avatar_inputs,
        lambda root: ["render", str(root / "avatar.ply"), "--pose", str(root / "pose.json"), "-o", str(root / "posed.png")],
        _pose_damages(),
    ),
    InputClass(
        "motion",
        _avatar_inputs,
        lambda root: [
            "render", str(root / "avatar.ply"), "--camera", str(root / "camera.json"),
            "--motion", str(root / "motion.npz"), "-o", str(root / "motion.mp4"),
        ],  # fmt: skip
        _motion_damages(),
    ),
    InputClass(
        "dataset",
        lambda root: write_dataset(root / "data"),
        lambda root: ["train-initial", str(root / "data"), str(root / "new-ws"), "--iterations", "1"],
        _dataset_damages(),
    ),
    InputClass(
        "workspace",
        _workspace_only,
        lambda root: ["render", str(root / "ws"), "--turntable", "2", "-o", str(root / "turntable.mp4")],
        {**_manifest_damages(), **_workspace_avatar_damages()},
    ),
    InputClass(
        "evaluate-test-video",
        _workspace_and_test,
        lambda root: ["evaluate", str(root / "ws"), "--test", str(root / "test")],
        _evaluate_damages(),
    ),
    InputClass(
        "edit-png",
        _edit_inputs,
        lambda root: ["apply-edit", str(root / "ws"), str(root / "edited.png"), "--pose", str(root / "pose.json")],
        _edit_damages(),
    ),
]

CASES: list[Case] = [case for input_class in INPUT_CLASSES for case in input_class.cases()]


# ------------------------------------------------------------------------ the newer stages and their outputs
# Outputs that must be refused before any work (unwritable, an existing file or folder, an unknown extension, a
# file the command did not write), bad option values, and the hand-edited manifest of every workspace stage.


def _report(output: str) -> Callable[[Path], list[str]]:
    return lambda root: ["report", str(root / "ws"), "--test", str(root / "test"), "-o", str(root / output)]


def _simulate_user(output: str) -> Callable[[Path], list[str]]:
    return lambda root: ["simulate-user", str(root / "ws"), "-o", str(root / output)]


def write_text(text: str) -> Damage:
    def make(path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)

    return make


def make_plain_folder(path: Path) -> None:
    path.mkdir(parents=True)
    (path / "notes.txt").write_text("a folder of the user's")


def nothing(path: Path) -> None:
    """The target is only named (an output path, a missing workspace)."""


def _region_inputs(root: Path) -> None:
    """_edit_inputs plus region.png, a selection over the painted square."""
    _edit_inputs(root)
    region = torch.zeros(HEIGHT, WIDTH, 1)
    region[2:6, 2:6] = 1.0
    write_image(root / "region.png", region)


def _huge_png_header(width: int, height: int) -> Damage:
    """A PNG whose header declares width x height RGB pixels and holds no pixel data."""

    def damage(path: Path) -> None:
        header = width.to_bytes(4, "big") + height.to_bytes(4, "big") + bytes([8, 2, 0, 0, 0])
        path.write_bytes(b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", header) + _png_chunk(b"IEND", b""))

    return damage


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return len(data).to_bytes(4, "big") + kind + data + zlib.crc32(kind + data).to_bytes(4, "big")


def _animation(suffix: str) -> Damage:
    """The painted image (edited.png beside the target) saved as a two-frame animation at the target path."""

    def damage(path: Path) -> None:
        with Image.open(path.parent / "edited.png") as first:
            frames = [first.convert("RGB"), first.convert("RGB").transpose(Image.Transpose.FLIP_LEFT_RIGHT)]
        frames[0].save(path, format=suffix, save_all=True, append_images=frames[1:])

    return damage


def _history(value: object) -> Damage:
    return edit_json(set_key("history", value=value))


def _edit_argv(*options: str) -> Callable[[Path], list[str]]:
    return lambda root: ["apply-edit", str(root / "ws"), *options]


def _newer_stage_cases() -> list[Case]:
    ws_json = "ws/workspace.json"
    cases = [
        Case("report/output an existing file", _damaged(_workspace_and_test, "out", write_text("mine")), _report("out")),
        Case("report/output under a file", _damaged(_workspace_and_test, "afile", write_text("mine")), _report("afile/report")),
        Case("report/metrics.png already there", _damaged(_workspace_and_test, "out/metrics.png", write_text("mine")), _report("out")),
        Case("simulate-user/output under a file", _damaged(_workspace_only, "afile", write_text("x")), _simulate_user("afile/p.png")),
        Case("simulate-user/output a folder", _damaged(_workspace_only, "p.png", make_plain_folder), _simulate_user("p.png")),
        Case("simulate-user/output without extension", _damaged(_workspace_only, "painted", nothing), _simulate_user("painted")),
        Case("simulate-user/output .xyz", _damaged(_workspace_only, "painted.xyz", nothing), _simulate_user("painted.xyz")),
        Case("simulate-user/its .json already there", _damaged(_workspace_only, "p.json", write_text("{}")), _simulate_user("p.png")),
        Case("simulate-user/output an existing file", _damaged(_workspace_only, "p.png", write_text("x")), _simulate_user("p.png")),
        Case(
            "simulate-user/output inside the workspace",
            _damaged(_workspace_only, "ws/suggestions/005/suggested.png", write_text("x")),
            _simulate_user("ws/suggestions/005/suggested.png"),
        ),
        Case("apply-edit/workspace missing", _damaged(_edit_inputs, "no/such/ws", nothing),
             lambda root: ["apply-edit", str(root / "no" / "such" / "ws"), str(root / "edited.png")]),  # fmt: skip
        Case("apply-edit/--erase bogus", _damaged(_region_inputs, "region.png", nothing),
             _edit_argv("--region", "REGION", "--erase", "bogus"), names="bogus"),  # fmt: skip
        Case("apply-edit/--fill rgb(300,0,0)", _damaged(_region_inputs, "region.png", nothing),
             _edit_argv("--region", "REGION", "--fill", "rgb(300,0,0)", "--pose", "POSE"), names="rgb(300,0,0)"),  # fmt: skip
        Case("edit-png/10000x10000 header", _damaged(_edit_inputs, "edited.png", _huge_png_header(10000, 10000)),
             _edit_argv("EDITED", "--pose", "POSE")),  # fmt: skip
        Case("edit-png/animated GIF", _damaged(_edit_inputs, "edited.gif", _animation("GIF")),
             _edit_argv("ROOT/edited.gif", "--pose", "POSE")),  # fmt: skip
        Case("edit-png/animated PNG", _damaged(_edit_inputs, "animated.png", _animation("PNG")),
             _edit_argv("ROOT/animated.png", "--pose", "POSE")),  # fmt: skip
        Case("prepare/empty .mp4", _damaged(lambda root: None, "empty.mp4", write_bytes(b"")), _prepare("empty.mp4")),
        Case("prepare/text .mp4", _damaged(lambda root: None, "text.mp4", write_text("not a video\n")), _prepare("text.mp4")),
        Case("prepare/output a folder of other files", _damaged(lambda root: write_text("x")(root / "walk.mp4"), "out", make_plain_folder),
             _prepare("walk.mp4")),  # fmt: skip
    ]
    for label, value in (("entry a string", ["oops"]), ("entry a number", [7]), ("a string", "abc")):
        for command, argv in (
            ("apply-edit --list", _edit_argv("--list")),
            ("refine", lambda root: ["refine", str(root / "ws")]),
            ("apply-edit --erase splat", _edit_argv("--region", "REGION", "--erase", "splat", "--pose", "POSE")),
        ):
            cases.append(Case(f"manifest history {label}/{command}", _damaged(_region_inputs, ws_json, _history(value)), argv))
    return [replace(case, argv=_placeholders(case.argv)) for case in cases]


def _prepare(video: str) -> Callable[[Path], list[str]]:
    return lambda root: ["prepare", str(root / video), str(root / "out")]


def _placeholders(argv: Callable[[Path], list[str]]) -> Callable[[Path], list[str]]:
    """argv with REGION, POSE, EDITED and ROOT/ spelled out under the case's root."""
    names = {"REGION": "region.png", "POSE": "pose.json", "EDITED": "edited.png"}

    def spelled(root: Path) -> list[str]:
        return [str(root / names[a]) if a in names else a.replace("ROOT/", f"{root}/") for a in argv(root)]

    return spelled


CASES += _newer_stage_cases()


def _body_fit_cases() -> list[Case]:
    """A training video whose mask leaves no body to fit: the body fit and the pose fit name the frame (the
    file itself is valid)."""
    fits = {"body-fit": ["--body-shape", "fit"], "pose-fit": ["--body-shape", "exact", "--refine-poses"]}
    mask = "data/masks/mask_0000.npy"

    def argv(options: list[str]) -> Callable[[Path], list[str]]:
        return lambda root: ["train-initial", f"{root}/data", f"{root}/new-ws", "--iterations", "1", *options]

    return [
        Case(f"{fit}/{label}", _damaged(lambda root: write_dataset(root / "data"), mask, save_npy(value)), argv(options), names="frame 0")
        for fit, options in fits.items()
        for label, value in (("mask empty", np.zeros((HEIGHT, WIDTH), np.uint8)), ("mask whole frame", np.ones((HEIGHT, WIDTH), np.uint8)))
    ]


CASES += _body_fit_cases()
