"""The `avatarperfect` command line. Each command parses arguments and calls one library function.

Heavy modules (torch, numba) are imported inside the commands so that `--help` stays fast.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Optional, TypeVar

import typer

if TYPE_CHECKING:
    from avatarperfect_cli.datasets import FrameRange

app = typer.Typer(
    help="Repair 3D Gaussian Splatting human avatars by painting 2D images.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

F = TypeVar("F", bound=Callable[..., object])


def _one_line_errors(command: F) -> F:
    """Print expected failures (AvatarPerfectError) as one line on stderr and exit with status 2."""

    @functools.wraps(command)
    def wrapper(*args: object, **kwargs: object) -> object:
        from avatarperfect_cli.errors import AvatarPerfectError

        try:
            return command(*args, **kwargs)
        except AvatarPerfectError as error:
            typer.echo(f"error: {error}", err=True)
            raise typer.Exit(2) from None
        except KeyboardInterrupt:
            typer.echo("interrupted: nothing was written", err=True)
            raise typer.Exit(130) from None

    return wrapper  # type: ignore[return-value]


def _not_implemented(name: str) -> None:
    typer.echo(f"error: '{name}' is not implemented yet", err=True)
    raise typer.Exit(1)


def _frame_range(text: Optional[str]) -> FrameRange | None:
    """'START:END[:STEP]' -> FrameRange, or None."""
    if text is None:
        return None
    from avatarperfect_cli.datasets import FrameRange
    from avatarperfect_cli.errors import AvatarPerfectError

    try:
        return FrameRange.parse(text)
    except ValueError as error:
        raise AvatarPerfectError(str(error)) from None


@app.command("make-sample")
@_one_line_errors
def make_sample(
    out_dir: Path = typer.Argument(..., help="Folder for the sample: OUT_DIR/train and OUT_DIR/test."),
    preset: str = typer.Option("default", help="Body shape and clothing preset."),
    resolution: int = typer.Option(512, help="Image side in pixels."),
    seed: int = typer.Option(0, help="Seed; the same seed gives byte-identical files."),
    train_frames: int = typer.Option(100, help="Frames of the training video (a 360° turn)."),
    test_frames: int = typer.Option(30, help="Frames of the held-out test video."),
) -> None:
    """Make the synthetic sample subject (anny body, procedural clothes) in the People-Snapshot layout."""
    from avatarperfect_cli.sample.generate import make_sample as make

    make(out_dir, preset, resolution, seed, train_frames, test_frames)


@app.command("train-initial")
@_one_line_errors
def train_initial(
    dataset: Path = typer.Argument(..., help="Video in the People-Snapshot layout."),
    workspace: Path = typer.Argument(..., help="Workspace folder to create."),
    iterations: int = typer.Option(2000, min=1, help="Training steps."),
    resolution: Optional[int] = typer.Option(None, min=16, help="Longest image side to train at (integer downscale)."),
    frames: Optional[str] = typer.Option(None, help="Frame range START:END[:STEP], END inclusive."),
    body_model: str = typer.Option("anny", help="anny (built in) or smpl (needs --smpl-model-dir)."),
    smpl_model_dir: Optional[Path] = typer.Option(None, help="Folder with your licensed SMPL model files."),
    sh_degree: int = typer.Option(1, min=0, max=3, help="Spherical-harmonics degree of the colours."),
    seed: int = typer.Option(0, help="Random seed."),
    refine_poses: bool = typer.Option(False, "--refine-poses", help="Also refine each frame's SMPL pose (real videos)."),
    force: bool = typer.Option(False, "--force", help="Replace an existing workspace."),
) -> None:
    """Fit the first avatar from a monocular video."""
    from avatarperfect_cli.stages.train_initial import BodySettings, InitialFit, VideoSettings
    from avatarperfect_cli.stages.train_initial import train_initial as run

    fit = InitialFit(
        VideoSettings(_frame_range(frames), resolution), BodySettings(body_model, smpl_model_dir), iterations, sh_degree, seed, refine_poses
    )
    run(dataset, workspace, fit, force)


@app.command("evaluate")
@_one_line_errors
def evaluate(
    workspace: Path = typer.Argument(..., help="Workspace folder."),
    test: Path = typer.Option(..., "--test", help="Held-out video in the People-Snapshot layout."),
    iteration: Optional[int] = typer.Option(None, help="Avatar iteration [default: latest]."),
    frames: Optional[str] = typer.Option(None, help="Frame range START:END[:STEP] of the test video."),
) -> None:
    """IoU, PSNR and SSIM on held-out poses."""
    from avatarperfect_cli.stages.evaluate import evaluate as run

    run(workspace, test, iteration, _frame_range(frames))


@app.command("render")
@_one_line_errors
def render(
    source: Path = typer.Argument(..., help="A workspace, an avatar PLY, or any 3DGS PLY (with --camera)."),
    output: Path = typer.Option(..., "--output", "-o", help="PNG image, .mp4 video, or a folder for frames."),
    camera: Optional[Path] = typer.Option(None, "--camera", "-c", help="Camera JSON: K, world_to_camera, width, height."),
    pose: Optional[Path] = typer.Option(None, "--pose", help="Pose JSON: body pose, translation and camera."),
    motion: Optional[Path] = typer.Option(None, "--motion", help="SMPL motion .npz (poses (N,72), trans (N,3))."),
    turntable: int = typer.Option(0, help="Frames of a camera circling the avatar."),
    iteration: Optional[int] = typer.Option(None, help="Workspace avatar iteration [default: latest]."),
    background: str = typer.Option("white", help="white, black or R,G,B in 0..1."),
    fps: float = typer.Option(30.0, help="Frame rate of videos."),
    device: str = typer.Option("auto", help="auto, cpu or cuda (static PLY renders)."),
) -> None:
    """Render static Gaussians, or a skinned avatar in a pose, a motion or a turntable."""
    from avatarperfect_cli.stages import render as stage

    if camera is not None and pose is None and motion is None and turntable == 0:
        stage.render_ply(source, camera, output, None, background, device)
    else:
        stage.render_avatar_views(source, output, pose, motion, turntable, camera, iteration, background, fps)


@app.command("visibility")
def visibility() -> None:
    """Accumulate per-Gaussian visibility over the video and past edits."""
    _not_implemented("visibility")


@app.command("suggest")
def suggest() -> None:
    """Suggest the next body pose and camera to edit, and render it."""
    _not_implemented("suggest")


@app.command("apply-edit")
def apply_edit() -> None:
    """Register a painted image: derive its mask and apply background deletions."""
    _not_implemented("apply-edit")


@app.command("refine")
def refine() -> None:
    """Re-optimise the avatar on the video plus every painted image."""
    _not_implemented("refine")
