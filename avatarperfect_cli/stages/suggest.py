"""The `suggest` stage: the next body pose and camera to paint, rendered for the user.

Writes ws/suggestions/NNN/ (numbered from 001, never reused), all at once:
    suggested.png    the avatar in the suggested pose on white, at the training resolution: paint this
    suggested_alpha.png  its accumulated opacity (a layer mask for editors)
    pose.json        body pose, translation and camera (what `render --pose` and `apply-edit --pose` read)
    guide.png        suggested.png with the pixels dominated by barely-seen Gaussians tinted and outlined
    suggestion.json  objective, angles, latent, mode, seed, avatar iteration, seconds
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from rich.console import Console
from rich.progress import Progress

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.devices import CPU
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.io import atomic_write_text, read_pose, write_image, write_pose
from avatarperfect_cli.io.atomic import atomic_folder
from avatarperfect_cli.io.workspace import locked_workspace
from avatarperfect_cli.refinement.collision import BodyCapsules
from avatarperfect_cli.refinement.pictures import guide_image
from avatarperfect_cli.refinement.pose_prior import load_pose_prior
from avatarperfect_cli.refinement.suggest import SuggestConfig, Suggestion, suggest_view
from avatarperfect_cli.refinement.visibility import DEFAULT_EDIT_WEIGHT, barely_seen
from avatarperfect_cli.render import rasterization
from avatarperfect_cli.stages.visibility import current_visibility
from avatarperfect_cli.stages.workspace_data import SUGGESTIONS, reference_pose

WHITE = torch.ones(3)


@dataclass
class SuggestSettings:
    """What `suggest` needs besides the workspace: the search, the pose prior, V's edit weight and the
    device the avatar is rendered on."""

    search: SuggestConfig = field(default_factory=SuggestConfig)
    pose_prior: str = "builtin"
    vposer_dir: Path | None = None
    edit_weight: float = DEFAULT_EDIT_WEIGHT
    device: torch.device = CPU


def suggest(workspace_root: Path, settings: SuggestSettings | None = None, progress: bool = True, hint: bool = True) -> Path:
    """Suggest the next view for the workspace's current avatar; returns the new suggestion folder. hint: print
    what to do next."""
    settings = settings or SuggestSettings()
    if settings.search.starts < 1 or settings.search.steps < 0 or settings.search.resolution < 16:
        raise AvatarPerfectError("suggest needs --starts >= 1, --steps >= 0 and --resolution >= 16")
    console = Console(stderr=True, quiet=not progress)
    with locked_workspace(workspace_root) as workspace:
        start = time.perf_counter()
        stored = Avatar.load(workspace.require_avatar())
        avatar = stored.to(settings.device)
        reference = reference_pose(workspace)
        prior = load_pose_prior(settings.pose_prior, reference.body_pose, settings.vposer_dir)
        record = current_visibility(workspace, avatar, settings.edit_weight, progress)
        capsules = BodyCapsules.from_points(stored.params["means"].detach(), stored.skin_weights.detach(), stored.rest_joints)
        earlier = [read_pose(folder / "pose.json") for folder in workspace.numbered_folders(SUGGESTIONS)]
        search = settings.search
        total = search.starts * search.steps if search.body_pose != "random" else 0
        with Progress(console=console, transient=True, disable=not progress) as bar:
            task = bar.add_task("searching pose and camera", total=total)
            suggestion = suggest_view(
                avatar, record.visibility, prior, capsules, reference, search, earlier, lambda: bar.advance(task)
            )
        folder = workspace.next_numbered_folder(SUGGESTIONS)
        with atomic_folder(folder) as staging:
            _write_suggestion(staging, avatar, record.visibility, suggestion)
            summary = {
                "iteration": workspace.iteration,
                "objective": suggestion.objective,
                "azimuth_deg": math.degrees(suggestion.azimuth),
                "elevation_deg": math.degrees(suggestion.elevation),
                "latent": suggestion.latent.tolist(),
                "pose_prior": settings.pose_prior,
                "search": asdict(search),
                "seconds": round(time.perf_counter() - start, 2),
            }
            atomic_write_text(staging / "suggestion.json", json.dumps(summary, indent=2) + "\n")
    console.print(
        f"suggestion {folder.name}: objective {suggestion.objective:.1f}, camera azimuth {summary['azimuth_deg']:.0f}°, "
        f"elevation {summary['elevation_deg']:.0f}° ({summary['seconds']:.1f} s)"
    )
    if hint:
        console.print(f"next: paint {folder / 'suggested.png'} (see guide.png for where to look), save it, then run")
        console.print(f"  avatarperfect apply-edit {workspace_root} EDITED.png", highlight=False)
    return folder


def _write_suggestion(folder: Path, avatar: Avatar, visibility: torch.Tensor, suggestion: Suggestion) -> None:
    pose = suggestion.pose
    with torch.no_grad():
        out = render_avatar(avatar, pose.body_pose, pose.transl, pose.camera, WHITE)
        means, quats = avatar.pose(pose.body_pose, pose.transl)
        barely = barely_seen(visibility).float()[:, None].to(avatar.device)
        share = rasterization(means, quats, avatar.scales, avatar.opacities, barely, pose.camera).image[..., 0].cpu()
    image, alpha = out.image.clamp(0, 1).cpu(), out.alpha.cpu()
    write_image(folder / "suggested.png", image)
    write_image(folder / "suggested_alpha.png", alpha[..., None])
    write_pose(folder / "pose.json", pose)
    dominated = (share > 0.5 * alpha) & (alpha > 0.1)
    write_image(folder / "guide.png", guide_image(image, dominated))
