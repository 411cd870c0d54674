"""The `render` stage: static Gaussians with a camera, or a skinned avatar posed by a pose, a motion or a turntable."""

from __future__ import annotations

import math
import os
import shutil
from pathlib import Path

import cv2
import torch
from rich.console import Console
from rich.progress import track

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.gaussians import Gaussians
from avatarperfect_cli.io import atomic_path, read_camera, read_gaussians, read_pose, write_image
from avatarperfect_cli.io.atomic import staging_dir
from avatarperfect_cli.io.camera_json import camera_from_json
from avatarperfect_cli.io.motion import read_motion
from avatarperfect_cli.io.workspace import open_workspace
from avatarperfect_cli.render import Camera, RenderOutput, rasterization

NAMED_BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


def parse_background(text: str) -> torch.Tensor:
    """'white', 'black' or 'R,G,B' with components in [0, 1] -> (3,) tensor."""
    if text in NAMED_BACKGROUNDS:
        return torch.tensor(NAMED_BACKGROUNDS[text])
    try:
        values = [float(part) for part in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not all(0.0 <= v <= 1.0 for v in values):
        raise AvatarPerfectError(f"background '{text}' is not white, black or R,G,B with values in 0..1")
    return torch.tensor(values)


def resolve_device(name: str) -> torch.device:
    """'auto' (CUDA when available), 'cpu' or 'cuda' -> a torch device."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name not in ("cpu", "cuda"):
        raise AvatarPerfectError(f"device '{name}' is not auto, cpu or cuda")
    if name == "cuda" and not torch.cuda.is_available():
        raise AvatarPerfectError("device 'cuda' was asked for but no CUDA GPU is available")
    return torch.device(name)


def render_gaussians(
    gaussians: Gaussians, camera: Camera, background: torch.Tensor, device: torch.device
) -> RenderOutput:
    """Render static Gaussians (their own SH degree) into one camera, without gradients."""
    gaussians = gaussians.to(device)
    with torch.no_grad():
        return rasterization(
            gaussians.means, gaussians.unit_quats, gaussians.scales, gaussians.opacities, gaussians.sh,
            camera.to(device=device), sh_degree=gaussians.sh_degree, background=background.to(device),
        )  # fmt: skip


def _require_png(output: Path) -> None:
    if output.suffix.lower() != ".png":
        raise AvatarPerfectError(f"{output}: the output must be a .png file")


def default_alpha_path(output: Path) -> Path:
    return output.with_name(f"{output.stem}_alpha.png")


def render_ply(
    source: Path,
    camera_path: Path,
    output: Path,
    alpha_output: Path | None = None,
    background: str = "white",
    device: str = "auto",
) -> None:
    """Render a Gaussian PLY with a camera JSON to an RGB PNG and an alpha PNG (both written atomically)."""
    _require_png(output)
    background_color, torch_device = parse_background(background), resolve_device(device)
    gaussians = read_gaussians(source)
    camera = read_camera(camera_path)
    out = render_gaussians(gaussians, camera, background_color, torch_device)
    write_image(output, out.image.clamp(0, 1).cpu())
    write_image(alpha_output or default_alpha_path(output), out.alpha.cpu())


def orbit_cameras(camera: Camera, center: torch.Tensor, count: int) -> list[Camera]:
    """`count` cameras circling `center` (3,) about the camera's own up axis, starting at `camera`."""
    rotation = camera.world_to_camera[:3, :3]
    up = -rotation[1]  # image up in world coordinates
    cameras = []
    for k in range(count):
        angle = 2 * math.pi * k / count
        cos, sin = math.cos(angle), math.sin(angle)
        cross = torch.tensor([[0, -up[2], up[1]], [up[2], 0, -up[0]], [-up[1], up[0], 0]])
        spin = cos * torch.eye(3) + sin * cross + (1 - cos) * torch.outer(up, up)  # Rodrigues about `up`
        view = camera.world_to_camera.clone()
        view[:3, :3] = rotation @ spin.T
        view[:3, 3] = -view[:3, :3] @ (center + spin @ (camera.center - center))
        cameras.append(Camera(camera.K, view, camera.width, camera.height))
    return cameras


def _avatar_and_camera(source: Path, iteration: int | None) -> tuple[Avatar, Camera | None, dict]:
    """An avatar from a workspace (latest or `iteration`) or an avatar PLY, with the workspace's camera."""
    if source.is_dir():
        workspace = open_workspace(source)
        avatar = Avatar.load(workspace.require_avatar(iteration))
        return avatar, camera_from_json(workspace.manifest["camera"], source / "workspace.json"), workspace.manifest
    return Avatar.load(source), None, {}


def _write_frames(output: Path, frames: list[torch.Tensor], fps: float) -> None:
    """An .mp4 (OpenCV, mp4v) or a folder of frame_NNNN.png; both appear only when complete."""
    if output.suffix.lower() == ".mp4":
        height, width = frames[0].shape[:2]
        with atomic_path(output) as temporary:
            writer = cv2.VideoWriter(str(temporary), cv2.VideoWriter_fourcc(*"mp4v"), fps, (width, height))
            if not writer.isOpened():
                raise AvatarPerfectError(f"{output}: OpenCV cannot write mp4 video here")
            for frame in frames:
                rgb = (frame.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()
                writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
            writer.release()
        return
    if output.suffix:
        raise AvatarPerfectError(f"{output}: give an .mp4 file or a folder for the frames")
    staging = staging_dir(output)
    try:
        for index, frame in enumerate(frames):
            write_image(staging / f"frame_{index:04d}.png", frame.clamp(0, 1))
        shutil.rmtree(output, ignore_errors=True)
        os.replace(staging, output)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def render_avatar_views(
    source: Path,
    output: Path,
    pose: Path | None = None,
    motion: Path | None = None,
    turntable: int = 0,
    camera_path: Path | None = None,
    iteration: int | None = None,
    background: str = "white",
    fps: float = 30.0,
    progress: bool = True,
) -> None:
    """Render a skinned avatar (workspace or avatar PLY) posed by a pose JSON, a motion file, or on a turntable.

    pose:      one image (the pose JSON's own camera) to `output` (.png)
    motion:    one frame per motion pose, seen by `camera_path` or the workspace's training camera; the
               motion starts where the training subject stood (its translation is taken relative to
               its first frame)
    turntable: that many frames of a camera circling the avatar in the training video's first pose
    """
    background_color = parse_background(background)
    if pose is not None:
        _require_png(output)
    avatar, camera, manifest = _avatar_and_camera(source, iteration)
    if camera_path is not None:
        camera = read_camera(camera_path)
    if pose is not None:
        pose_file = read_pose(pose)
        with torch.no_grad():
            out = render_avatar(avatar, pose_file.body_pose, pose_file.transl, pose_file.camera, background_color)
        write_image(output, out.image.clamp(0, 1))
        write_image(default_alpha_path(output), out.alpha)
        return
    if camera is None:
        raise AvatarPerfectError(f"{source}: an avatar PLY needs --camera for --motion and --turntable")
    reference = manifest.get("reference_pose", {"body_pose": [[0.0] * 3] * 24, "transl": [0.0, 0.0, 0.0]})
    reference_pose, reference_transl = torch.tensor(reference["body_pose"]), torch.tensor(reference["transl"])
    if motion is not None:
        body_poses, transl = read_motion(motion)
        transl = transl - transl[:1] + reference_transl
        views = [(body_poses[t], transl[t], camera) for t in range(len(body_poses))]
    elif turntable > 0:
        center = reference_transl + avatar.rest_joints[0]
        views = [(reference_pose, reference_transl, c) for c in orbit_cameras(camera, center, turntable)]
    else:
        raise AvatarPerfectError("a skinned avatar needs one of --pose, --motion or --turntable")
    frames = []
    with torch.no_grad():
        for body_pose, translation, view_camera in track(views, description="rendering", console=Console(stderr=True), disable=not progress):
            frames.append(render_avatar(avatar, body_pose, translation, view_camera, background_color).image)
    _write_frames(output, frames, fps)
