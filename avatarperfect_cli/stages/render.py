"""The `render` stage: static Gaussians with a camera, or a skinned avatar posed by a pose, a motion or a turntable.

Every output is checked before anything is rendered. Images come in pairs (X.png and X_alpha.png) that
appear together or not at all. Motions and turntables stream their frames, as they are rendered, into an
.mp4 or a folder of frame_0000.png, ... that appears only when complete (io/video.py says which folders
may take them).
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from rich.console import Console
from rich.progress import track

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.body import axis_angle_to_matrix
from avatarperfect_cli.devices import CPU
from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.gaussians import Gaussians
from avatarperfect_cli.io import read_camera, read_gaussians, read_pose
from avatarperfect_cli.io.motion import UP_AXES, detect_up_axis, place_motion, read_motion
from avatarperfect_cli.io.outputs import check_new_output, write_image_pair
from avatarperfect_cli.io.pose_json import NUM_JOINTS
from avatarperfect_cli.io.video import check_video_output, frame_writer
from avatarperfect_cli.io.workspace import MANIFEST, open_workspace
from avatarperfect_cli.render import Camera, RenderOutput, rasterization
from avatarperfect_cli.stages.workspace_data import reference_pose, training_camera

NAMED_BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
EMPTY_ALPHA = 0.5 / 255  # a render whose alpha stays below this is the bare background once written in 8 bits


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


def default_alpha_path(output: Path) -> Path:
    return output.with_name(f"{output.stem}_alpha.png")


def _warn(message: str) -> None:
    """One line on stderr (no wrapping)."""
    Console(stderr=True, soft_wrap=True).print(f"[yellow]warning[/]: {message}", markup=True, highlight=False)


def _is_empty(out: RenderOutput) -> bool:
    """True when nothing of the Gaussians shows in the render (it is the background only)."""
    return float(out.alpha.max()) < EMPTY_ALPHA


def render_ply(
    source: Path,
    camera_path: Path,
    output: Path,
    alpha_output: Path | None = None,
    background: str = "white",
    device: torch.device = CPU,
    force: bool = False,
) -> None:
    """Render a Gaussian PLY with a camera JSON on `device` to an RGB PNG and an alpha PNG (written together,
    atomically).

    Both outputs are checked before any work (existing files are replaced only with `force`); a warning goes to
    stderr when the camera sees none of the Gaussians.
    """
    alpha_output = alpha_output or default_alpha_path(output)
    check_new_output(output, (".png",), force)
    check_new_output(alpha_output, (".png",), force)
    background_color = parse_background(background)
    gaussians = read_gaussians(source)
    camera = read_camera(camera_path)
    out = render_gaussians(gaussians, camera, background_color, device)
    if _is_empty(out):
        _warn(f"{output}: the camera sees none of the Gaussians of {source}; the image is only background")
    write_image_pair(output, out.image.clamp(0, 1).cpu(), alpha_output, out.alpha.cpu())


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


def _avatar_and_reference(
    source: Path, iteration: int | None
) -> tuple[Avatar, Camera | None, tuple[torch.Tensor, torch.Tensor]]:
    """An avatar from a workspace (latest or `iteration`) or an avatar PLY, with the workspace's camera and
    reference pose (body_pose (24, 3), transl (3,)); an avatar PLY has no camera and the rest pose at 0."""
    if source.is_dir():
        workspace = open_workspace(source)
        camera, reference = training_camera(workspace), reference_pose(workspace)
        if not (reference.body_pose.isfinite().all() and reference.transl.isfinite().all()):
            raise InputFileError(workspace.root / MANIFEST, "'reference_pose' holds NaN or Inf")
        return Avatar.load(workspace.require_avatar(iteration)), camera, (reference.body_pose, reference.transl)
    return Avatar.load(source), None, (torch.zeros(NUM_JOINTS, 3), torch.zeros(3))


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
    force: bool = False,
    up: str | None = None,
    device: torch.device = CPU,
) -> None:
    """Render a skinned avatar (workspace or avatar PLY) on `device`, posed by a pose JSON, a motion file, or on
    a turntable.

    pose:      one image (the pose JSON's own camera) to `output` (.png) and its alpha beside it
    motion:    one frame per motion pose, seen by `camera_path` or the workspace's training camera, placed
               by io.motion.place_motion: upright (the motion's up axis `up`, a key of UP_AXES, or detected
               from its first frame), facing the camera, its first frame's root where the training video's
               first frame had it (the origin for an avatar PLY), and its root path relative to its first
               frame, turned the same way
    turntable: that many frames of a camera circling the avatar in the training video's first pose
    Frames stream to an .mp4 or a frames folder (`force`: see the module doc). Outputs are checked before
    any work; a warning goes to stderr for renders that show none of the avatar.
    """
    background_color = parse_background(background)
    if up is not None and (motion is None or up not in UP_AXES):
        raise AvatarPerfectError(f"--up {up}: give y, -y or z, with --motion")
    if pose is not None:
        check_new_output(output, (".png",), force)
        check_new_output(default_alpha_path(output), (".png",), force)
    else:
        if motion is None and turntable == 0:
            raise AvatarPerfectError("a skinned avatar needs one of --pose, --motion or --turntable")
        if turntable < 0 or (motion is not None and turntable):
            raise AvatarPerfectError("give either --motion or --turntable with a positive number of frames")
        if not (math.isfinite(fps) and fps > 0):
            raise AvatarPerfectError(f"--fps must be a positive number, got {fps}")
        check_video_output(output, force)
    avatar, camera, (reference_body_pose, reference_transl) = _avatar_and_reference(source, iteration)
    if camera_path is not None:
        camera = read_camera(camera_path)
    if pose is not None:
        pose_file = read_pose(pose)
        avatar = avatar.to(device)
        with torch.no_grad():
            out = render_avatar(avatar, pose_file.body_pose, pose_file.transl, pose_file.camera, background_color)
        if _is_empty(out):
            _warn(f"{output}: the pose's camera sees none of the avatar; the image is only background")
        write_image_pair(output, out.image.clamp(0, 1).cpu(), default_alpha_path(output), out.alpha.cpu())
        return
    if camera is None:
        raise AvatarPerfectError(f"{source}: an avatar PLY needs --camera for --motion and --turntable")
    if motion is not None:
        body_poses, transl = read_motion(motion)
        world_up = axis_angle_to_matrix(reference_body_pose[0])[:, 1]  # how the training subject stood
        toward_camera = camera.center - (reference_transl + avatar.rest_joints[0])
        body_poses, transl = place_motion(
            body_poses, transl, up or detect_up_axis(body_poses, motion), world_up, toward_camera, reference_transl
        )
        views = [(body_poses[t], transl[t], camera) for t in range(len(body_poses))]
    else:
        center = reference_transl + avatar.rest_joints[0]
        views = [(reference_body_pose, reference_transl, c) for c in orbit_cameras(camera, center, turntable)]
    empty = 0
    console = Console(stderr=True)
    avatar = avatar.to(device)
    with frame_writer(output, camera.width, camera.height, fps) as write, torch.no_grad():
        for body_pose, translation, view_camera in track(views, "rendering", console=console, disable=not progress):
            out = render_avatar(avatar, body_pose, translation, view_camera, background_color)
            empty += _is_empty(out)
            write(out.image.cpu())
    if empty:
        _warn(f"{output}: {empty} of {len(views)} frames show none of the avatar (the camera looks away from it)")
