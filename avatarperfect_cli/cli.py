"""The `avatarperfect` command line. Each command parses arguments and calls one library function.

Heavy modules (torch, numba) are imported inside the commands so that `--help` stays fast.
"""

from __future__ import annotations

import functools
import math
import signal
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
DEVICE_HELP = "auto (cuda when torch sees a CUDA GPU, else cpu), cpu or cuda: where the avatar is rendered and trained."


def _is_interrupt(error: BaseException) -> bool:
    """True for Ctrl-C and SIGTERM, also when one surfaced inside a compiled numba kernel as a SystemError
    or after an interrupt signal turned into another exception."""
    from avatarperfect_cli import interrupts

    if interrupts.received():
        return True
    seen: set[int] = set()
    current: BaseException | None = error
    while current is not None and id(current) not in seen:
        if isinstance(current, KeyboardInterrupt):
            return True
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return False


_options = {"verbose": False}  # the options before the command, set by `_global_options` on every invocation


@app.callback()
def _global_options(
    verbose: bool = typer.Option(
        False, "--verbose", help="Also show the libraries' own log lines and warnings (FFmpeg, TFLite, absl, Pillow) on stderr."
    ),
) -> None:
    """Repair 3D Gaussian Splatting human avatars by painting 2D images."""
    _options["verbose"] = verbose


def _one_line_errors(command: F) -> F:
    """Print expected failures (AvatarPerfectError) as one line on stderr and exit with status 2;
    Ctrl-C and SIGTERM end with "interrupted" and status 130, after the stage has cleaned up.
    The libraries' own output stays off stderr unless --verbose (see `library_output`)."""

    @functools.wraps(command)
    def wrapper(*args: object, **kwargs: object) -> object:
        import contextlib

        from avatarperfect_cli import interrupts
        from avatarperfect_cli.errors import AvatarPerfectError
        from avatarperfect_cli.library_output import libraries_quiet

        interrupts.install((signal.SIGTERM,))  # the entry point routes SIGINT too
        try:
            with contextlib.nullcontext() if _options["verbose"] else libraries_quiet():
                return command(*args, **kwargs)
        except AvatarPerfectError as error:
            typer.echo(f"error: {error}", err=True)
            raise typer.Exit(2) from None
        except (KeyboardInterrupt, Exception) as error:
            if not _is_interrupt(error):
                raise
            typer.echo("interrupted: nothing was changed", err=True)
            raise typer.Exit(130) from None

    return wrapper  # type: ignore[return-value]


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


def _require_in_range(option: str, value: float | None, low: float, high: float | None = None) -> None:
    """One-line AvatarPerfectError unless low <= value (<= high); None passes (an unset option)."""
    from avatarperfect_cli.errors import AvatarPerfectError

    if value is not None and (value < low or (high is not None and value > high)):
        allowed = f"from {low} to {high}" if high is not None else f"at least {low}"
        raise AvatarPerfectError(f"{option} must be {allowed}, got {value}")


def _phenotype(text: str | None) -> dict[str, float] | None:
    """'NAME=VALUE,...' -> {NAME: VALUE}, checked against anny's phenotypes; None stays None."""
    if text is None:
        return None
    from avatarperfect_cli.body.anny_model import full_phenotype
    from avatarperfect_cli.errors import AvatarPerfectError

    values = {}
    for item in text.split(","):
        name, equals, value = item.partition("=")
        try:
            values[name.strip()] = float(value) if equals else math.nan
        except ValueError:
            values[name.strip()] = math.nan
        if not math.isfinite(values[name.strip()]):
            raise AvatarPerfectError(f"--body '{text}': '{item}' is not NAME=VALUE with a number")
    full_phenotype(values)
    return values


@app.command("make-sample")
@_one_line_errors
def make_sample(
    out_dir: Path = typer.Argument(..., help="Folder for the sample: OUT_DIR/train and OUT_DIR/test."),
    preset: str = typer.Option("default", help="Body shape and clothing preset."),
    resolution: int = typer.Option(512, help="Image side in pixels."),
    seed: int = typer.Option(0, help="Seed; the same seed gives byte-identical files."),
    train_frames: int = typer.Option(100, help="Frames of the training video (a 360° turn)."),
    test_frames: int = typer.Option(30, help="Frames of the held-out test video."),
    body: Optional[str] = typer.Option(
        None, help="Another anny body for the preset's clothes: NAME=VALUE,... over gender, age, muscle, weight, "
        "height and proportions, each in [0, 1], missing ones 0.5 (e.g. 'height=0.65,weight=0.25')."
    ),  # fmt: skip
) -> None:
    """Make the synthetic sample subject (anny body, procedural clothes) in the People-Snapshot layout."""
    from avatarperfect_cli.io.camera_json import max_image_side
    from avatarperfect_cli.io.outputs import check_writable_folder
    from avatarperfect_cli.sample.generate import MIN_RESOLUTION
    from avatarperfect_cli.sample.generate import make_sample as make

    _require_in_range("--resolution", resolution, MIN_RESOLUTION, max_image_side())
    phenotype = _phenotype(body)
    check_writable_folder(out_dir)
    make(out_dir, preset, resolution, seed, train_frames, test_frames, phenotype)


@app.command("prepare")
@_one_line_errors
def prepare(
    video: Path = typer.Argument(..., help="A video of one person (any format OpenCV reads, e.g. .mp4)."),
    out_dir: Path = typer.Argument(
        ..., help="Folder the command writes, in the People-Snapshot layout: new, empty, or a previous one (replaced); a "
        "folder with other files is refused before any frame is decoded.",
    ),  # fmt: skip
    every: int = typer.Option(1, help="Keep every N-th frame."),
    fov: Optional[float] = typer.Option(
        None, help="The camera's field of view across the longer image side, degrees. Default: from the 35 mm-equivalent "
        "focal length the video records (iPhones do), else 60 (assumed).",
    ),  # fmt: skip
    max_side: int = typer.Option(
        1080, help="Frames longer than this many pixels on their longer side are shrunk to it (0: keep the video's size)."
    ),
    max_frames: int = typer.Option(
        300, help="A clip that would keep more frames keeps every N-th for the smallest N that leaves at most this many "
        "(0: no limit).",
    ),  # fmt: skip
) -> None:
    """Make a People-Snapshot folder from your own video: frames, person masks, fitted SMPL poses, a camera
    (needs MediaPipe's pose models: the package's optional extra 'prepare'; see docs/real-data.md)."""
    from avatarperfect_cli.io.outputs import check_writable_folder
    from avatarperfect_cli.sample.generate import MIN_RESOLUTION
    from avatarperfect_cli.stages.prepare import PrepareSettings
    from avatarperfect_cli.stages.prepare import prepare as run

    _require_in_range("--every", every, 1)
    _require_in_range("--max-frames (or 0: no limit)", max_frames, 0)
    if max_side != 0:
        _require_in_range("--max-side (or 0: the video's size)", max_side, MIN_RESOLUTION)
    check_writable_folder(out_dir)
    run(video, out_dir, PrepareSettings(every=every, fov_degrees=fov, max_side=max_side, max_frames=max_frames))


@app.command("train-initial")
@_one_line_errors
def train_initial(
    dataset: Path = typer.Argument(..., help="Video in the People-Snapshot layout."),
    workspace: Path = typer.Argument(..., help="Workspace folder to create."),
    iterations: int = typer.Option(2000, help="Training steps (at least 1)."),
    resolution: Optional[int] = typer.Option(None, help="Longest image side to train at (>= 16; integer downscale)."),
    frames: Optional[str] = typer.Option(
        None, help="Frame range START:END[:STEP], END inclusive (default: every frame, or the split file's frames)."
    ),
    poses: str = typer.Option(
        "auto", help="Pose file, relative to DATASET or absolute (default: poses/anim_nerf_train.npz, else "
        "poses_optimized.npz, else poses.npz).", show_default=False,
    ),  # fmt: skip
    body_model: str = typer.Option("anny", help="anny (built in) or smpl (needs --smpl-model-dir)."),
    smpl_model_dir: Optional[Path] = typer.Option(None, help="Folder with your licensed SMPL model files."),
    transl_offset: str = typer.Option(
        "auto", help="Added to the dataset's translations so the template lands on the subject: auto (fitted to the "
        "masks when the poses were fitted for another body, e.g. SMPL poses with anny), fit, off, or X,Y,Z metres.",
    ),  # fmt: skip
    body_shape: str = typer.Option(
        "auto", help="fit: fit the body (anny's phenotype, or SMPL's betas as given, and the skeleton) to the masks; "
        "exact: the dataset's own body (a synthetic sample's subject.json, SMPL's betas); auto: exact when the "
        "dataset names the template's body, else fit.",
    ),  # fmt: skip
    sh_degree: int = typer.Option(1, help="Spherical-harmonics degree of the colours (0 to 3)."),
    seed: int = typer.Option(0, help="Random seed."),
    max_gaussians: int = typer.Option(
        60_000, help="Densification stops growing the avatar at this many Gaussians (a 512² video grows to about "
        "52,000; 30,000 trains a quarter faster with the same held-out score, but refine then has fewer to repaint).",
    ),  # fmt: skip
    refine_poses: Optional[bool] = typer.Option(
        None, "--refine-poses/--no-refine-poses", help="Correct estimated poses: fit each frame's pose to its mask (keeping "
        "the motion smooth), then refine it with the avatar against the image. Default: on when the dataset says its "
        "poses are estimated (prepare's folders), off otherwise.", show_default=False,
    ),  # fmt: skip
    force: bool = typer.Option(False, "--force", help="Replace an existing workspace."),
    device: str = typer.Option("auto", help=DEVICE_HELP),
) -> None:
    """Fit the first avatar from a monocular video."""
    from avatarperfect_cli.devices import resolve_device
    from avatarperfect_cli.io.outputs import check_writable_folder
    from avatarperfect_cli.sample.generate import MIN_RESOLUTION
    from avatarperfect_cli.errors import AvatarPerfectError
    from avatarperfect_cli.stages.train_initial import BODY_SHAPES, BodySettings, InitialFit, VideoSettings, parse_transl_offset
    from avatarperfect_cli.stages.train_initial import train_initial as run

    torch_device = resolve_device(device)
    _require_in_range("--iterations", iterations, 1)
    _require_in_range("--resolution", resolution, MIN_RESOLUTION)
    _require_in_range("--sh-degree", sh_degree, 0, 3)
    _require_in_range("--max-gaussians", max_gaussians, 1)
    check_writable_folder(workspace)
    if body_shape not in BODY_SHAPES:
        raise AvatarPerfectError(f"--body-shape '{body_shape}' is not one of {', '.join(BODY_SHAPES)}")
    body = BodySettings(body_model, smpl_model_dir, parse_transl_offset(transl_offset), body_shape)
    video = VideoSettings(_frame_range(frames), resolution, poses)
    fit = InitialFit(video, body, iterations, sh_degree, seed, refine_poses, torch_device, max_gaussians)
    run(dataset, workspace, fit, force)


@app.command("evaluate")
@_one_line_errors
def evaluate(
    workspace: Path = typer.Argument(..., help="Workspace folder."),
    test: Path = typer.Option(
        ..., "--test", help="Held-out video (People-Snapshot layout) at the training video's resolution; another is refused."
    ),
    iteration: Optional[int] = typer.Option(None, help="Avatar iteration [default: latest]."),
    frames: Optional[str] = typer.Option(
        None, help="Frame range START:END[:STEP] of the test video (default: every frame, or the split file's frames)."
    ),
    poses: str = typer.Option(
        "auto", help="Pose file, relative to the test video or absolute (default: poses/anim_nerf_test.npz, else "
        "poses_optimized.npz, else poses.npz).", show_default=False,
    ),  # fmt: skip
    device: str = typer.Option("auto", help=DEVICE_HELP),
    refine_poses: bool = typer.Option(
        False, "--refine-poses", help="Also score with each held-out pose fitted to its frame (mask, then image, from whichever of "
        "the two poses matches the image better) with the avatar fixed, so estimated test poses do not count against the avatar; both scores are reported.",
    ),  # fmt: skip
) -> None:
    """IoU, PSNR and SSIM on held-out poses (moved by the workspace's translation offset, like its training poses)."""
    from avatarperfect_cli.devices import resolve_device
    from avatarperfect_cli.stages.evaluate import evaluate as run

    torch_device = resolve_device(device)
    run(workspace, test, iteration, _frame_range(frames), poses=poses, device=torch_device, refine_poses=refine_poses)


@app.command("render")
@_one_line_errors
def render(
    source: Path = typer.Argument(..., help="A workspace, an avatar PLY, or any 3DGS PLY (with --camera)."),
    output: Path = typer.Option(
        ..., "--output", "-o",
        help="What the command writes: a PNG image (and X_alpha.png beside it), an .mp4 video, or a folder for "
        "frame_NNNN.png: a new or empty folder, or a previous frames output. Existing files, or a folder with other "
        "files, need --force.",
    ),  # fmt: skip
    camera: Optional[Path] = typer.Option(
        None, "--camera", "-c",
        help="Camera JSON: K, world_to_camera, width, height (sides up to 8192 px, or $AVATARPERFECT_MAX_IMAGE_SIDE).",
    ),  # fmt: skip
    pose: Optional[Path] = typer.Option(None, "--pose", help="Pose JSON: body pose, translation and camera."),
    motion: Optional[Path] = typer.Option(
        None, "--motion", help="SMPL motion .npz (poses (N,72), trans (N,3)), rendered upright and facing the camera. Its "
        "first frame's root is placed where the training video's first frame had it (the origin for an avatar PLY), "
        "also with --camera; later frames follow the motion's own root path from there, turned the same way.",
    ),  # fmt: skip
    up: Optional[str] = typer.Option(
        None, "--up", help="The motion's up axis: y (SMPL, GART), -y (camera frame, InstantAvatar) or z (AMASS) "
        "(default: detected from its first frame's root orientation).", show_default=False,
    ),  # fmt: skip
    turntable: int = typer.Option(0, help="Frames of a camera circling the avatar."),
    iteration: Optional[int] = typer.Option(None, help="Workspace avatar iteration [default: latest]."),
    background: str = typer.Option("white", help="white, black or R,G,B in 0..1."),
    fps: float = typer.Option(30.0, help="Frame rate of videos."),
    device: str = typer.Option("auto", help=DEVICE_HELP),
    force: bool = typer.Option(
        False, "--force", help="Replace an existing image or video, or write frames into a folder that holds other files "
        "(they are kept; its frame_NNNN.png are replaced)."
    ),
) -> None:
    """Render static Gaussians, or a skinned avatar in a pose, a motion or a turntable."""
    from avatarperfect_cli.devices import resolve_device
    from avatarperfect_cli.stages import render as stage

    torch_device = resolve_device(device)
    if camera is not None and pose is None and motion is None and turntable == 0 and up is None:
        stage.render_ply(source, camera, output, None, background, torch_device, force=force)
    else:
        stage.render_avatar_views(
            source, output, pose, motion, turntable, camera, iteration, background, fps, force=force, up=up, device=torch_device
        )


@app.command("visibility")
@_one_line_errors
def visibility(
    workspace: Path = typer.Argument(..., help="Workspace folder."),
    edit_weight: float = typer.Option(0.01, help="Weight w of the edit views in V (the paper: 0.01)."),
    device: str = typer.Option("auto", help=DEVICE_HELP),
) -> None:
    """Accumulate per-Gaussian visibility over the video and past edits (ws/visibility/NNN.npz + .png)."""
    from avatarperfect_cli.devices import resolve_device
    from avatarperfect_cli.stages.visibility import visibility as run

    torch_device = resolve_device(device)
    run(workspace, edit_weight, device=torch_device)


@app.command("suggest")
@_one_line_errors
def suggest(
    workspace: Path = typer.Argument(..., help="Workspace folder."),
    body_pose: str = typer.Option("optimise", help="optimise (pose and camera), canonical (camera only) or random."),
    random_view: bool = typer.Option(False, "--random", help="A random natural pose and camera (same as --body-pose random)."),
    pose_prior: str = typer.Option("builtin", help="builtin (joint limits, free) or vposer (needs --vposer-dir)."),
    vposer_dir: Optional[Path] = typer.Option(None, help="Folder with your licensed VPoser v2 checkpoint."),
    starts: int = typer.Option(3, help="Optimisation starts (the best of many random cameras), the best kept."),
    steps: int = typer.Option(30, help="Optimisation steps per start."),
    resolution: int = typer.Option(128, help="Longest image side while optimising, pixels."),
    max_elevation: float = typer.Option(20.0, help="Highest camera angle above or below the video camera's horizon, degrees."),
    edit_weight: float = typer.Option(0.01, help="Weight w of the edit views in V."),
    exposure_poses: int = typer.Option(
        32, help="Random natural poses that weigh each Gaussian by how much animations show it; 0: the paper's objective."
    ),
    seed: int = typer.Option(0, help="Seed; the same seed gives the same suggestion."),
    device: str = typer.Option("auto", help=DEVICE_HELP),
) -> None:
    """Suggest the next body pose and camera to paint, and render it (ws/suggestions/NNN/)."""
    from avatarperfect_cli.devices import resolve_device
    from avatarperfect_cli.refinement.suggest import SuggestConfig
    from avatarperfect_cli.stages.suggest import SuggestSettings
    from avatarperfect_cli.stages.suggest import suggest as run

    _require_in_range("--max-elevation", max_elevation, 0.0, 89.0)
    _require_in_range("--exposure-poses", exposure_poses, 0)
    torch_device = resolve_device(device)
    search = SuggestConfig(
        body_pose="random" if random_view else body_pose, starts=starts, steps=steps, resolution=resolution,
        max_elevation_deg=max_elevation, exposure_poses=exposure_poses, seed=seed,
    )  # fmt: skip
    run(workspace, SuggestSettings(search, pose_prior, vposer_dir, edit_weight, torch_device))


@app.command("apply-edit")
@_one_line_errors
def apply_edit(
    workspace: Path = typer.Argument(..., help="Workspace folder."),
    edited: Optional[Path] = typer.Argument(None, help="Your painted image (PNG; JPEG works with a warning)."),
    pose: Optional[Path] = typer.Option(None, "--pose", help="Pose JSON the image was rendered in [default: the latest suggestion]."),
    mask: Optional[Path] = typer.Option(None, "--mask", help="Your own edit mask (white = edited) instead of the difference."),
    region: Optional[Path] = typer.Option(None, "--region", help="A selection mask (white = selected) for --fill or --erase."),
    fill: Optional[str] = typer.Option(None, "--fill", help="Fill --region: a colour (white, #rrggbb, R,G,B), telea, ns or diffusion."),
    model_dir: Optional[Path] = typer.Option(None, "--model-dir", help="Your local Stable-Diffusion inpainting pipeline, for --fill diffusion."),
    prompt: str = typer.Option("", "--prompt", help="Text prompt for --fill diffusion."),
    erase: Optional[str] = typer.Option(None, "--erase", help="SuperSplat baseline: delete Gaussians in --region: center or splat (writes the next avatar iteration)."),
    list_edits: bool = typer.Option(False, "--list", help="List the registered edits (read-only: works while another stage runs)."),
    remove: Optional[int] = typer.Option(None, "--remove", help="Withdraw edit N."),
    strength: str = typer.Option(
        "default", "--strength", help="default, or strong: the edit wins over the video where they disagree (refine reports when an edit did not take)."
    ),
    edit_number: Optional[int] = typer.Option(None, "--edit", help="With --strength: change registered edit N's strength."),
) -> None:
    """Register a painted image as an edit (white = background, other colours = colour targets)."""
    from avatarperfect_cli.stages import apply_edit as stage

    if list_edits:
        stage.list_edits(workspace)
    elif remove is not None:
        stage.remove_edit(workspace, remove)
    elif edit_number is not None:
        stage.set_edit_strength(workspace, edit_number, strength)
    elif erase is not None:
        stage.erase_region(workspace, _required(region, "--erase needs --region MASK.png"), erase, pose)
    elif fill is not None:
        stage.fill_region(workspace, _required(region, "--fill needs --region MASK.png"), fill, pose, model_dir, prompt)
    else:
        stage.apply_edit(
            workspace, _required(edited, "give the painted image: avatarperfect apply-edit WS EDITED.png"), pose, mask, strength=strength
        )


@app.command("refine")
@_one_line_errors
def refine(
    workspace: Path = typer.Argument(..., help="Workspace folder."),
    iterations: int = typer.Option(500, help="Training steps (the paper: 500)."),
    edit_probability: float = typer.Option(0.3, help="Share of steps that train on an edit (the paper: 0.3)."),
    new_edit_share: float = typer.Option(0.5, help="Share of the edit steps that go to the edits not trained on before."),
    uniform_edits: bool = typer.Option(False, "--uniform-edits", help="Draw every edit alike instead (the paper)."),
    keep_shapes: bool = typer.Option(
        False, "--keep-shapes", help="Edits leave the Gaussians' scales and rotations alone (guards the video's look)."
    ),
    edit_loss_weight: float = typer.Option(
        0.25, help="An edit step's loss against a video step's (the paper: 1): edits move less what the video shows well."
    ),
    slow_barely_seen: bool = typer.Option(
        False, "--slow-barely-seen", help="Gaussians the video barely saw move and reshape as slowly as the rest (by default as in the first fit)."
    ),
    no_split: bool = typer.Option(
        False, "--no-split", help="Keep the Gaussian count: do not split the large barely seen Gaussians under a new edit's strokes."
    ),
    seed: int = typer.Option(0, help="Random seed."),
    revert_to: Optional[int] = typer.Option(None, "--revert-to", help="Make avatar iteration K current again (keeps the others)."),
    delete_seen: bool = typer.Option(
        False, "--delete-seen", help="Background strokes delete every Gaussian centred under them, also ones the video saw well."
    ),
    template_skinning: float = typer.Option(
        1.0, help="Most of the way the skinning weights move to the body template's at each Gaussian first (0: keep the learned ones)."
    ),
    template_shift_mm: float = typer.Option(
        3.0, help="...but no further than shifts a Gaussian this far in any training frame, mm (inf: no limit)."
    ),
    no_reanchor: bool = typer.Option(
        False, "--no-reanchor", help="Keep the canonical means and orientations when the skinning moves (every Gaussian then moves only as the shift bound allows)."
    ),
    smpl_model_dir: Optional[Path] = typer.Option(None, help="Folder with your licensed SMPL model files (SMPL avatars)."),
    device: str = typer.Option("auto", help=DEVICE_HELP),
) -> None:
    """Re-optimise the avatar on the video plus every painted image (writes the next avatar iteration)."""
    from avatarperfect_cli.devices import resolve_device
    from avatarperfect_cli.refinement.additional_training import SPLIT_PAINTED
    from avatarperfect_cli.stages import refine as stage

    torch_device = resolve_device(device)
    if revert_to is not None:
        stage.revert(workspace, revert_to)
    else:
        share = None if uniform_edits else new_edit_share
        settings = stage.RefineSettings(
            iterations, edit_probability, seed, protect_seen=not delete_seen, new_edit_share=share, keep_shapes=keep_shapes,
            edit_loss_weight=edit_loss_weight, barely_seen_rates=not slow_barely_seen, split_painted=None if no_split else SPLIT_PAINTED,
            template_skinning=template_skinning, template_shift=template_shift_mm / 1e3, reanchor=not no_reanchor,
            smpl_model_dir=smpl_model_dir,
            device=torch_device,
        )  # fmt: skip
        stage.refine(workspace, settings)


@app.command("loop")
@_one_line_errors
def loop(
    workspace: Path = typer.Argument(..., help="Workspace folder."),
    rounds: int = typer.Option(5, help="Rounds of suggest, paint, apply-edit and refine."),
    editor: Optional[str] = typer.Option(
        None, "--editor", help="Command that opens the image to paint each round (the file is appended), e.g. 'gimp' or 'krita'."
    ),
    painted: Optional[Path] = typer.Option(
        None, "--painted", help="The file you save your painting as, each round [default: any new image in the suggestion's folder]."
    ),
    iterations: int = typer.Option(500, help="Training steps of each refine."),
    starts: int = typer.Option(3, help="Optimisation starts of each suggest."),
    steps: int = typer.Option(30, help="Optimisation steps per start of each suggest."),
    resolution: int = typer.Option(128, help="Longest image side while suggest optimises, pixels."),
    seed: int = typer.Option(0, help="Seed of suggest and refine."),
    device: str = typer.Option("auto", help=DEVICE_HELP),
) -> None:
    """Rounds of the loop for a person at an image editor: suggest, wait for the painting, register it, refine."""
    import sys

    from avatarperfect_cli.devices import resolve_device
    from avatarperfect_cli.refinement.additional_training import RefineSettings
    from avatarperfect_cli.refinement.suggest import SuggestConfig
    from avatarperfect_cli.stages.loop import LoopSettings
    from avatarperfect_cli.stages.loop import loop as run
    from avatarperfect_cli.stages.suggest import SuggestSettings

    torch_device = resolve_device(device)
    search = SuggestConfig(starts=starts, steps=steps, resolution=resolution, seed=seed)
    settings = LoopSettings(
        rounds, editor, painted, SuggestSettings(search, device=torch_device),
        RefineSettings(iterations=iterations, seed=seed, device=torch_device),
    )  # fmt: skip
    run(workspace, settings, keys=sys.stdin)


@app.command("relink")
@_one_line_errors
def relink(
    workspace: Path = typer.Argument(..., help="Workspace folder."),
    dataset: Path = typer.Argument(..., help="The workspace's training video in its new place (People-Snapshot layout)."),
) -> None:
    """Point a workspace at its moved training video, after checking it is the same video (frames, size, content)."""
    from avatarperfect_cli.stages.relink import relink as run

    run(workspace, dataset)


@app.command("simulate-user")
@_one_line_errors
def simulate_user(
    workspace: Path = typer.Argument(..., help="Workspace of a synthetic subject made by make-sample."),
    subject: Optional[Path] = typer.Option(None, "--subject", help="The make-sample folder [default: the workspace's dataset]."),
    style: str = typer.Option("exact", help="exact (true colours) or flat (each blob's mean colour, the inpaint tool)."),
    budget: float = typer.Option(0.15, help="Most pixels painted, as a share of the subject's pixels."),
    priority: str = typer.Option(
        "error", help="Which wrong regions first: error (most summed difference) or area (most pixels)."
    ),
    outline_tolerance: float = typer.Option(
        0.006, help="Largest displacement overlooked, as a share of the image height (0: judge pixel by pixel)."
    ),
    truth_pose: str = typer.Option(
        "avatar", help="The truth compared with: avatar (the subject where the avatar's skeleton stands) or "
        "suggested (the subject in the suggested joint angles on its own skeleton).",
    ),  # fmt: skip
    output: Optional[Path] = typer.Option(
        None, "--output", "-o", help="The painted .png outside the workspace; its statistics go beside it (same name, "
        ".json). These two files are what the command writes [default: the suggestion's simulated_edit.png and .json].",
    ),  # fmt: skip
    force: bool = typer.Option(False, "--force", help="Replace the -o image and its .json if they exist."),
) -> None:
    """Paint the latest suggestion as a careful person would (synthetic subjects only), for apply-edit."""
    from avatarperfect_cli.sample.simulated_user import UserConfig
    from avatarperfect_cli.stages.simulate_user import simulate_user as run

    config = UserConfig(style=style, budget=budget, priority=priority, outline_tolerance=outline_tolerance, truth_pose=truth_pose)
    run(workspace, subject, config, output, force=force)


@app.command("report")
@_one_line_errors
def report(
    workspace: Path = typer.Argument(..., help="Workspace folder."),
    test: Path = typer.Option(..., "--test", help="Held-out video in the People-Snapshot layout."),
    output: Path = typer.Option(
        ..., "--output", "-o", help="Folder (new or existing) for metrics.png, suggestions.png and comparison.mp4, the "
        "files this command writes (it also adds the missing evaluations to the workspace's eval/).",
    ),  # fmt: skip
    force: bool = typer.Option(False, "--force", help="Replace metrics.png, suggestions.png and comparison.mp4 already in the folder."),
) -> None:
    """Pictures of the refinement loop: held-out metrics per iteration, the edits, a before/after video."""
    from avatarperfect_cli.stages.report import report as run

    run(workspace, test, output, force=force)


def _required(value: Optional[Path], message: str) -> Path:
    from avatarperfect_cli.errors import AvatarPerfectError

    if value is None:
        raise AvatarPerfectError(message)
    return value
