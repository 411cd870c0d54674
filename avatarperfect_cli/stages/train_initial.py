"""The `train-initial` stage: fit the first avatar from a monocular video into a new workspace."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.body import BodyTemplate, load_body_template
from avatarperfect_cli.body.anny_model import build_anny_template, default_cache_dir, load_anny_model
from avatarperfect_cli.datasets import FrameRange, VideoDataset, load_people_snapshot, read_dataset_camera, video_fingerprint
from avatarperfect_cli.datasets.people_snapshot import downscaled_camera
from avatarperfect_cli.devices import CPU
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.io.atomic import atomic_path
from avatarperfect_cli.io import write_image
from avatarperfect_cli.io.camera_json import camera_to_json
from avatarperfect_cli.io.workspace import check_new_workspace, new_workspace, workspace_lock
from avatarperfect_cli.training.body_fit import BodyFitConfig, fit_body, fit_picture
from avatarperfect_cli.training.pose_fit import PoseFitConfig, fit_poses_to_masks
from avatarperfect_cli.training.pose_refinement import PoseRefiner
from avatarperfect_cli.training.silhouette import SkinnedPoints, check_masks
from avatarperfect_cli.training.strategy import DensifyConfig
from avatarperfect_cli.training.template_offset import OffsetSearch, fit_transl_offset
from avatarperfect_cli.training.trainer import TrainConfig, train, video_views

# With --refine-poses: the video's refined poses (frame_ids (T,), body_pose (T, 24, 3), transl (T, 3)).
REFINED_POSES = "poses.npz"


# --transl-offset: fit it when the poses were fitted for another body (auto), always (fit), or take it as given.
AUTO_OFFSET, FIT_OFFSET = "auto", "fit"
# --body-shape: fit the body to the masks, take the dataset's (exact), or fit unless the dataset names its body (auto).
BODY_SHAPES = ("auto", "fit", "exact")
# The picture of the body and pose fit in the workspace: the start and the fitted body over training masks.
BODY_FIT_PICTURE = "body_fit.png"
# the longest image side avatars of people are usually trained at (People-Snapshot's 1080 px frames halved)
TYPICAL_RESOLUTION = 540
BODY_TEMPLATE = "body_template.npz"  # the body the avatar was built on, so no later stage rebuilds it


def parse_transl_offset(text: str) -> str | tuple[float, float, float]:
    """'auto', 'fit', 'off' (no offset) or 'X,Y,Z' in metres -> AUTO_OFFSET, FIT_OFFSET or the offset."""
    if text in (AUTO_OFFSET, FIT_OFFSET):
        return text
    if text == "off":
        return (0.0, 0.0, 0.0)
    try:
        values = tuple(float(part) for part in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(np.isfinite(values)):
        raise AvatarPerfectError(f"--transl-offset '{text}' is not auto, fit, off or X,Y,Z in metres")
    return values  # type: ignore[return-value]


@dataclass
class VideoSettings:
    """Which part of a People-Snapshot folder to use, at which size.

    frames:     frame range, None for every frame (or, with a split file, the split's frames)
    resolution: longest image side in pixels after integer downscaling; None keeps the native size
    poses:      "auto" (poses/anim_nerf_train.npz, else poses_optimized.npz, else poses.npz) or a pose file,
                relative to the dataset or absolute
    """

    frames: FrameRange | None = None
    resolution: int | None = None
    poses: str = "auto"

    def downscale(self, root: Path, resolution: int | None = None) -> int:
        """The integer factor for `resolution` (default: this one's); 1 keeps the native size."""
        resolution = resolution or self.resolution
        if resolution is None:
            return 1
        camera = read_dataset_camera(root)
        return max(1, round(max(camera.width, camera.height) / resolution))

    def load(self, root: Path, resolution: int | None = None) -> VideoDataset:
        """The training split at this resolution, or at `resolution` pixels when given."""
        return load_people_snapshot(root, self.frames, "train", self.downscale(root, resolution), pose_source=self.poses)


@dataclass
class BodySettings:
    """The body model the avatar's template comes from. A dataset's subject.json takes precedence.

    transl_offset: what to add to the dataset's translations so the template lands on the subject
                   (training/template_offset.py): AUTO_OFFSET fits it when the template is not SMPL and the
                   dataset's poses were not made for it (no subject.json naming its body model), FIT_OFFSET
                   always fits it, a tuple gives it in metres (world frame); with a body fit it is where the
                   fit starts, and the fit moves it in the image plane
    shape:         "fit" fits the body to the masks (training/body_fit.py: anny's phenotype, or SMPL's
                   betas as given, with a skeleton correction), "exact" takes the dataset's body (subject.json's
                   anny phenotype, SMPL's betas, else anny's middle phenotype), "auto" is exact when the
                   dataset's subject.json names the template's body and fit otherwise
    """

    name: str = "anny"
    smpl_model_dir: Path | None = None
    transl_offset: str | tuple[float, float, float] = AUTO_OFFSET
    shape: str = "auto"

    def fits_shape(self, video: VideoDataset) -> bool:
        """Whether to fit the body to the video's masks (see `shape`)."""
        if self.shape not in BODY_SHAPES:
            raise AvatarPerfectError(f"unknown body shape {self.shape!r}; choose one of {', '.join(BODY_SHAPES)}")
        subject = video.subject or {}
        names_body = subject.get("body_model") == self.name == "anny" and "body" not in subject.get("estimated", [])
        return self.shape == "fit" or (self.shape == "auto" and not names_body)

    def template(self, video: VideoDataset) -> tuple[BodyTemplate, dict]:
        """The template and the JSON description stored in the avatar (the start of a body fit)."""
        subject = video.subject or {}
        if subject.get("body_model") == "anny" and not self.fits_shape(video):
            phenotype = subject.get("phenotype")
            return load_body_template("anny", phenotype=phenotype), {"name": "anny", "phenotype": phenotype}
        if self.name == "smpl":
            betas = video.betas.tolist()
            template = load_body_template("smpl", smpl_model_dir=self.smpl_model_dir, betas=betas)
            return template, {"name": "smpl", "betas": betas}
        return load_body_template(self.name), {"name": self.name}

    def needs_offset(self, body_model: dict, video: VideoDataset) -> bool:
        """Whether to fit the translation offset: always (FIT_OFFSET), or (AUTO_OFFSET) when the template is
        not SMPL and the dataset's subject.json does not name its body model as the one its poses are for."""
        if isinstance(self.transl_offset, tuple):
            return False
        poses_for_template = body_model["name"] == "smpl" or (video.subject or {}).get("body_model") == body_model["name"]
        return self.transl_offset == FIT_OFFSET or not poses_for_template


@dataclass
class InitialFit:
    """Everything `train-initial` needs besides the paths; `device` is where the avatar is trained (the
    translation-offset search and the written results stay on the CPU)."""

    video: VideoSettings = field(default_factory=VideoSettings)
    body: BodySettings = field(default_factory=BodySettings)
    iterations: int = 2000
    sh_degree: int = 1
    seed: int = 0
    # fit the poses to the masks, then refine them with the avatar; None: when the dataset's subject.json says
    # its poses are estimated ("estimated": ["poses", ...], as `prepare` writes)
    refine_poses: bool | None = None

    def refines_poses(self, video: VideoDataset) -> bool:
        """Whether to fit and refine the video's poses (see `refine_poses`)."""
        if self.refine_poses is not None:
            return self.refine_poses
        return "poses" in (video.subject or {}).get("estimated", [])
    device: torch.device = CPU
    # densification stops growing the avatar at this many Gaussians (`DensifyConfig.max_gaussians`)
    max_gaussians: int = field(default_factory=lambda: DensifyConfig().max_gaussians)


def train_initial(dataset: Path, workspace: Path, fit: InitialFit, force: bool = False, progress: bool = True) -> Path:
    """Fit an avatar to the video in `dataset` and create `workspace` with avatar/000.ply.

    The workspace appears only when everything succeeded (an interrupted run leaves nothing).
    Returns the avatar's path.
    """
    if fit.iterations < 1:
        raise AvatarPerfectError(f"iterations must be at least 1, got {fit.iterations}")
    with workspace_lock(workspace):
        return _train_initial(dataset, workspace, fit, force, progress)


def _transl_offset(
    dataset: Path, fit: InitialFit, video: VideoDataset, template: BodyTemplate, body_model: dict, console: Console,
    search: bool = False,
) -> torch.Tensor:  # fmt: skip
    """(3,) metres added to the video's translations (BodySettings.transl_offset), searched for when the
    settings ask for it or `search`; a searched one is measured on masks of at least the search's resolution
    (the training video's, or a finer load of the same frames)."""
    if isinstance(fit.body.transl_offset, tuple):
        return torch.tensor(fit.body.transl_offset, dtype=torch.float32)
    if not (search or fit.body.needs_offset(body_model, video)):
        return torch.zeros(3)
    search = OffsetSearch()
    fine_enough = max(video.camera.width, video.camera.height) >= search.resolution
    masks = video if fine_enough else fit.video.load(dataset, search.resolution)
    result = fit_transl_offset(template, masks, search)
    x, y, z = result.offset.tolist()
    console.print(
        f"template offset ({x:+.3f}, {y:+.3f}, {z:+.3f}) m puts the {body_model['name']} template on the masks "
        f"(mean IoU {result.iou:.2f}); --transl-offset sets it",
        soft_wrap=True,
    )
    return result.offset


def _fit_body(
    video: VideoDataset, start: BodyTemplate, body_model: dict, offset: torch.Tensor, anny: object | None,
    progress: bool, console: Console, with_poses: bool,
) -> tuple[BodyTemplate, dict, torch.Tensor]:  # fmt: skip
    """The body fitted to the video's masks from the `start` template at `offset`, anny's phenotype with
    `anny` (a loaded model): the fitted template, its description and the offset (3,). With `with_poses`
    the video's poses are fitted together with the body and replace its own, in place (the translations
    without the offset)."""
    config, poses = BodyFitConfig(), PoseFitConfig() if with_poses else None
    steps = config.steps(len(config.starts) if anny is not None else 1, with_poses)
    clock = time.perf_counter()
    with Progress(TextColumn("[bold]fitting the body" + (" and the poses" if with_poses else "")), BarColumn(),
                  MofNCompleteColumn(), TimeElapsedColumn(), console=Console(stderr=True), transient=True,
                  disable=not progress) as bar:  # fmt: skip
        task = bar.add_task("body", total=steps)
        result = fit_body(video, offset, config, anny_model=anny, template=None if anny else start, poses=poses,
                          on_step=lambda: bar.advance(task))  # fmt: skip
    if result.body_pose is not None:
        video.body_pose, video.transl = result.body_pose, result.transl - result.transl_offset
    described = dict(body_model)
    if anny is not None:
        described["phenotype"] = result.phenotype
        fitted = build_anny_template(anny, result.phenotype)
    else:
        fitted = start
    fitted = fitted.with_bone_offsets(result.bone_offsets)
    described["bone_offsets"] = result.bone_offsets.tolist()
    shape = ", ".join(f"{name} {value:.2f}" for name, value in result.phenotype.items())
    console.print(
        f"body{' and poses' if with_poses else ''} fitted to the masks in {time.perf_counter() - clock:.0f} s: silhouette distance "
        f"{result.start_loss:.2f} -> {result.loss:.2f} px" + (f" ({shape})" if shape else ""),
        soft_wrap=True,
    )
    return fitted, described, result.transl_offset


def _fit_poses(video: VideoDataset, template: BodyTemplate, progress: bool, console: Console) -> torch.Tensor:
    """Fit the video's poses (translations with their offset) to its masks, in place; returns the translation
    correction (3,) all frames share, metres, which belongs to the offset (the held-out frames need it too)."""
    config = PoseFitConfig()
    start = time.perf_counter()
    with Progress(TextColumn("[bold]fitting the poses"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=Console(stderr=True), transient=True, disable=not progress) as bar:  # fmt: skip
        task = bar.add_task("poses", total=config.steps)
        result = fit_poses_to_masks(video, SkinnedPoints.of_template(template, config.points), config, on_step=lambda: bar.advance(task))
    shared = (result.transl - video.transl).float().mean(dim=0)
    video.body_pose, video.transl = result.body_pose, result.transl
    console.print(
        f"poses fitted to the masks in {time.perf_counter() - start:.0f} s: silhouette distance "
        f"{result.start_loss:.2f} -> {result.loss:.2f} px",
        soft_wrap=True,
    )
    return shared


def _train_initial(dataset: Path, workspace: Path, fit: InitialFit, force: bool, progress: bool) -> Path:
    check_new_workspace(workspace, force)
    console = Console(stderr=True, quiet=not progress)
    video = fit.video.load(dataset)
    for note in video.notes:
        console.print(note, soft_wrap=True, markup=False, highlight=False)
    template, body_model = fit.body.template(video)
    fits_shape, refine_poses = fit.body.fits_shape(video), fit.refines_poses(video)
    if fits_shape or refine_poses:
        check_masks(video)
    offset = _transl_offset(dataset, fit, video, template, body_model, console, search=fits_shape)
    start_row = (template, video.body_pose, video.transl + offset)
    anny = load_anny_model(default_cache_dir()) if fits_shape and body_model["name"] == "anny" else None
    if fits_shape:
        template, body_model, offset = _fit_body(video, template, body_model, offset, anny, progress, console, refine_poses)
    video.transl = video.transl + offset
    if refine_poses and not fits_shape:
        offset = offset + _fit_poses(video, template, progress, console)
    picture = None
    if fits_shape or refine_poses:
        picture, (iou_start, iou_fitted) = fit_picture(video, [start_row, (template, video.body_pose, video.transl)])
        console.print(f"silhouette IoU with the masks {iou_start:.3f} -> {iou_fitted:.3f} ({BODY_FIT_PICTURE} shows both)")
    avatar = Avatar.from_template(template, sh_degree=fit.sh_degree, body_model=body_model).to(fit.device)
    console.print(f"fitting {len(avatar):,} Gaussians to {len(video)} frames of {video.camera.width}x{video.camera.height}")
    factor = round(max(video.camera.width, video.camera.height) / TYPICAL_RESOLUTION)
    if fit.video.resolution is None and factor >= 2:
        smaller = downscaled_camera(video.camera, factor)
        console.print(f"(--resolution {TYPICAL_RESOLUTION} would train at {smaller.width}x{smaller.height}, on {factor**2} times fewer pixels)")
    config = TrainConfig(iterations=fit.iterations, seed=fit.seed)
    config.densify.max_gaussians = fit.max_gaussians
    config.learning_rates.total_steps = fit.iterations
    refiner = PoseRefiner(len(video), device=fit.device) if refine_poses else None
    start = time.perf_counter()
    train(avatar, video_views(video), config=config, progress=progress, pose_refiner=refiner)
    seconds = time.perf_counter() - start
    manifest = {
        "dataset": str(Path(dataset).resolve()),
        "dataset_fingerprint": asdict(video_fingerprint(dataset)),
        "frames": None if fit.video.frames is None else asdict(fit.video.frames),
        "poses": video.pose_file,
        "transl_offset": offset.tolist(),
        "downscale": fit.video.downscale(dataset),
        "camera": camera_to_json(video.camera),
        "body_model": body_model,
        "reference_pose": {"body_pose": video.body_pose[0].tolist(), "transl": video.transl[0].tolist()},
        "iteration": 0,
        "history": [{"stage": "train-initial", "avatar": 0, "iterations": fit.iterations, "seed": fit.seed, "seconds": round(seconds, 1), "gaussians": len(avatar)}],
    }
    manifest["body_template"] = BODY_TEMPLATE
    if refiner is not None:
        manifest["refined_poses"] = REFINED_POSES
    with new_workspace(workspace, manifest, force) as staged:
        staged.set_dataset(dataset)  # relative to the staging folder, a sibling of `workspace`: the same path
        avatar.save(staged.avatar_path(0))
        template.save(staged.root / BODY_TEMPLATE)
        if picture is not None:
            write_image(staged.root / BODY_FIT_PICTURE, torch.from_numpy(picture))
        if refiner is not None:
            body_pose, transl = refiner.refined(video.body_pose, video.transl)
            with atomic_path(staged.root / REFINED_POSES) as temporary, open(temporary, "wb") as handle:
                np.savez(handle, frame_ids=video.frame_ids.numpy(), body_pose=body_pose.numpy(), transl=transl.numpy())
    console.print(f"wrote {workspace / 'avatar' / '000.ply'} ({len(avatar):,} Gaussians, {seconds:.0f} s)")
    return workspace / "avatar" / "000.ply"
