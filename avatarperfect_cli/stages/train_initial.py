"""The `train-initial` stage: fit the first avatar from a monocular video into a new workspace."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from rich.console import Console

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.body import BodyTemplate, load_body_template
from avatarperfect_cli.datasets import FrameRange, VideoDataset, load_people_snapshot, read_dataset_camera, video_fingerprint
from avatarperfect_cli.devices import CPU
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.io.atomic import atomic_path
from avatarperfect_cli.io.camera_json import camera_to_json
from avatarperfect_cli.io.workspace import check_new_workspace, new_workspace, workspace_lock
from avatarperfect_cli.training.pose_refinement import PoseRefiner
from avatarperfect_cli.training.template_offset import OffsetSearch, fit_transl_offset
from avatarperfect_cli.training.trainer import TrainConfig, train, video_views

# With --refine-poses: the video's refined poses (frame_ids (T,), body_pose (T, 24, 3), transl (T, 3)).
REFINED_POSES = "poses.npz"


# --transl-offset: fit it when the poses were fitted for another body (auto), always (fit), or take it as given.
AUTO_OFFSET, FIT_OFFSET = "auto", "fit"


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
                   always fits it, a tuple gives it in metres (world frame)
    """

    name: str = "anny"
    smpl_model_dir: Path | None = None
    transl_offset: str | tuple[float, float, float] = AUTO_OFFSET

    def template(self, video: VideoDataset) -> tuple[BodyTemplate, dict]:
        """The template and the JSON description stored in the avatar."""
        subject = video.subject or {}
        if subject.get("body_model") == "anny":
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
    refine_poses: bool = False  # per-frame pose refinement, for real videos with approximate poses
    device: torch.device = CPU


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
    dataset: Path, fit: InitialFit, video: VideoDataset, template: BodyTemplate, body_model: dict, console: Console
) -> torch.Tensor:
    """(3,) metres added to the video's translations (BodySettings.transl_offset); a fitted one is measured
    on masks of at least the search's resolution (the training video's, or a finer load of the same frames)."""
    if isinstance(fit.body.transl_offset, tuple):
        return torch.tensor(fit.body.transl_offset, dtype=torch.float32)
    if not fit.body.needs_offset(body_model, video):
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


def _train_initial(dataset: Path, workspace: Path, fit: InitialFit, force: bool, progress: bool) -> Path:
    check_new_workspace(workspace, force)
    console = Console(stderr=True, quiet=not progress)
    video = fit.video.load(dataset)
    for note in video.notes:
        console.print(note, soft_wrap=True, markup=False, highlight=False)
    template, body_model = fit.body.template(video)
    offset = _transl_offset(dataset, fit, video, template, body_model, console)
    video.transl = video.transl + offset
    avatar = Avatar.from_template(template, sh_degree=fit.sh_degree, body_model=body_model).to(fit.device)
    console.print(f"fitting {len(avatar):,} Gaussians to {len(video)} frames of {video.camera.width}x{video.camera.height}")
    config = TrainConfig(iterations=fit.iterations, seed=fit.seed)
    config.learning_rates.total_steps = fit.iterations
    refiner = PoseRefiner(len(video), device=fit.device) if fit.refine_poses else None
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
    if refiner is not None:
        manifest["refined_poses"] = REFINED_POSES
    with new_workspace(workspace, manifest, force) as staged:
        staged.set_dataset(dataset)  # relative to the staging folder, a sibling of `workspace`: the same path
        avatar.save(staged.avatar_path(0))
        if refiner is not None:
            body_pose, transl = refiner.refined(video.body_pose, video.transl)
            with atomic_path(staged.root / REFINED_POSES) as temporary, open(temporary, "wb") as handle:
                np.savez(handle, frame_ids=video.frame_ids.numpy(), body_pose=body_pose.numpy(), transl=transl.numpy())
    console.print(f"wrote {workspace / 'avatar' / '000.ply'} ({len(avatar):,} Gaussians, {seconds:.0f} s)")
    return workspace / "avatar" / "000.ply"
