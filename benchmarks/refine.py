"""refine on the synthetic sample: speed, one colour edit, one background edit (issue 8's measurements).

    python -m benchmarks.refine WORKSPACE SAMPLE_DIR [--images docs/images]

WORKSPACE: a workspace trained on SAMPLE_DIR/train (e.g. `make demo`'s after train-initial). On a copy:
  colour edit:     the current avatar's suggestion, the simulated user (its default budget: 15% of the
                   subject's pixels) painting true colours where the colours are wrong (colour strokes
                   only); after one 500-step refine, PSNR inside the edit mask against the painted
                   colours, and PSNR on the training frames;
  background edit: white painted where the avatar shows something the subject does not have, by a user
                   without a budget, on the first suggestion (seeds 0, 1, ...) with at least 50 px of it
                   (else a 32 px square at the avatar's silhouette edge);
                   after one refine, the alpha left in the painted region, and a check that every deleted
                   Gaussian's centre projects into the painted region;
  speed:           wall time and steps per second of the refines.
Writes a before/after figure per edit to --images.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.io import read_image, read_pose, write_image
from avatarperfect_cli.io.workspace import open_workspace
from avatarperfect_cli.refinement.erase import centres_in_region
from avatarperfect_cli.refinement.suggest import SuggestConfig
from avatarperfect_cli.sample.simulated_user import UserConfig, paint
from avatarperfect_cli.sample.subject import SyntheticSubject
from avatarperfect_cli.stages.apply_edit import apply_edit
from avatarperfect_cli.stages.refine import RefineSettings, refine
from avatarperfect_cli.stages.suggest import SuggestSettings, suggest
from avatarperfect_cli.stages.workspace_data import load_video
from avatarperfect_cli.training import metrics

WHITE = torch.ones(3)


def training_psnr(avatar: Avatar, ws: Path) -> float:
    video = load_video(open_workspace(ws))
    with torch.no_grad():
        return statistics.fmean(
            metrics.psnr(render_avatar(avatar, video.body_pose[t], video.transl[t], video.camera, WHITE).image.clamp(0, 1), video.images[t])
            for t in range(len(video))
        )


def render_at(ws: Path, pose) -> tuple[torch.Tensor, torch.Tensor]:
    avatar = Avatar.load(open_workspace(ws).require_avatar())
    with torch.no_grad():
        out = render_avatar(avatar, pose.body_pose, pose.transl, pose.camera, WHITE)
    return out.image.clamp(0, 1), out.alpha


MIN_STROKE = 50  # px of white strokes a background edit needs


def masked_psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    return metrics.psnr(a[mask], b[mask])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("workspace", type=Path)
    parser.add_argument("sample", type=Path)
    parser.add_argument("--images", type=Path, default=Path("docs/images"))
    parser.add_argument("--background-seeds", type=int, default=8, help="suggestion seeds tried for white strokes")
    args = parser.parse_args()
    scratch = Path(tempfile.mkdtemp(prefix="refine-bench-"))
    subject = SyntheticSubject.from_dataset(args.sample / "train")
    base = scratch / "base"
    shutil.copytree(args.workspace, base, ignore=shutil.ignore_patterns("suggestions", "edits", "visibility", "eval"))
    folder = suggest(base, progress=False)
    pose = read_pose(folder / "pose.json")
    suggested = read_image(folder / "suggested.png", "RGB")
    alpha = read_image(folder / "suggested_alpha.png", "L")[..., 0]
    # the sample's own body: the suggested pose is the one the user pictures; judged pixel by pixel, as the
    # figures of docs/refine.md were
    result = paint(suggested, alpha, subject.render(pose.body_pose, pose.transl, pose.camera), UserConfig(outline_tolerance=0.0))
    initial_train = training_psnr(Avatar.load(open_workspace(base).require_avatar()), base)
    rows: list[tuple[str, ...]] = []
    args.images.mkdir(parents=True, exist_ok=True)

    # colour edit: keep only the colour strokes
    colour = base.parent / "colour"
    shutil.copytree(base, colour)
    painted_white = (result.image >= 0.99).all(dim=-1) & (result.stroke_weight >= 0.5)
    colour_image = torch.where((result.stroke_weight > 0)[..., None] & ~painted_white[..., None], result.image, suggested)
    write_image(scratch / "colour.png", colour_image)
    edit = apply_edit(colour, scratch / "colour.png", progress=False)
    mask = read_image(edit / "mask.png", "L")[..., 0] >= 0.5
    target = read_image(edit / "target.png", "RGB")
    start = time.perf_counter()
    refine(colour, RefineSettings(), progress=False)
    colour_seconds = time.perf_counter() - start
    after, _ = render_at(colour, pose)
    before_psnr, after_psnr = masked_psnr(suggested, target, mask), masked_psnr(after, target, mask)
    colour_train = training_psnr(Avatar.load(open_workspace(colour).require_avatar()), colour)
    write_image(args.images / "refine_colour_edit.png", torch.cat([suggested, colour_image, after], dim=1))
    rows.append(("colour edit", f"{int(mask.sum())} px", f"PSNR in mask {before_psnr:.2f} -> {after_psnr:.2f} dB ({after_psnr - before_psnr:+.2f})",
                 f"training PSNR {initial_train:.2f} -> {colour_train:.2f} dB ({colour_train - initial_train:+.2f})", f"{colour_seconds:.1f} s"))  # fmt: skip

    # background edit: the white strokes of a painter without a budget, on the first suggestion (seeds 0, 1,
    # ...) where they cover at least MIN_STROKE px; else a square at the silhouette's edge
    background = base.parent / "background"
    shutil.copytree(args.workspace, background, ignore=shutil.ignore_patterns("suggestions", "edits", "visibility", "eval"))
    for seed in range(args.background_seeds):
        folder = suggest(background, SuggestSettings(SuggestConfig(seed=seed)), progress=False)
        pose = read_pose(folder / "pose.json")
        suggested = read_image(folder / "suggested.png", "RGB")
        alpha = read_image(folder / "suggested_alpha.png", "L")[..., 0]
        strokes = paint(suggested, alpha, subject.render(pose.body_pose, pose.transl, pose.camera), UserConfig(budget=1.0, outline_tolerance=0.0))
        region = (strokes.image >= 0.99).all(dim=-1) & (strokes.stroke_weight >= 0.5) & (alpha > 0.05)
        if int(region.sum()) >= MIN_STROKE:
            source = f"white strokes, suggestion seed {seed}"
            break
    else:
        rows_any = (alpha > 0.5).any(dim=1).nonzero()[:, 0]
        cols = (alpha[int(rows_any.float().mean())] > 0.5).nonzero()[:, 0]
        top, left = int(rows_any.float().mean()) - 16, int(cols[0]) - 8
        region = torch.zeros_like(alpha, dtype=torch.bool)
        region[top : top + 32, left : left + 32] = True
        source = f"32 px square at the silhouette's edge (no suggestion of seeds 0-{args.background_seeds - 1} had {MIN_STROKE} px of white strokes)"
    background_image = torch.where(region[..., None], WHITE, suggested)
    write_image(scratch / "background.png", background_image)
    edit = apply_edit(background, scratch / "background.png", progress=False)
    painted_background = read_image(edit / "background.png", "L")[..., 0] >= 0.5
    avatar_before = Avatar.load(open_workspace(background).require_avatar())
    expected = centres_in_region(avatar_before, pose, painted_background)
    start = time.perf_counter()
    refine(background, RefineSettings(), progress=False)
    background_seconds = time.perf_counter() - start
    entry = open_workspace(background).manifest["history"][-1]
    after, after_alpha = render_at(background, pose)
    _, before_alpha = render_at(args.workspace, pose)
    background_train = training_psnr(Avatar.load(open_workspace(background).require_avatar()), background)
    write_image(args.images / "refine_background_edit.png", torch.cat([suggested, background_image, after], dim=1))
    rows.append((f"background edit ({source})", f"{int(painted_background.sum())} px",
                 f"alpha in region: max {float(before_alpha[painted_background].max()):.3f} -> {float(after_alpha[painted_background].max()):.3f}, "
                 f"mean {float(before_alpha[painted_background].mean()):.3f} -> {float(after_alpha[painted_background].mean()):.4f}; "
                 f"deleted {entry['deleted']} (centres in region: {int(expected.sum())})",
                 f"training PSNR {initial_train:.2f} -> {background_train:.2f} dB ({background_train - initial_train:+.2f})",
                 f"{background_seconds:.1f} s"))  # fmt: skip
    gaussians = entry["gaussians"]
    print("edit | edited pixels | result | training frames | refine wall time (500 steps)")
    for row in rows:
        print(" | ".join(row))
    print(f"\nrefine: {500 / statistics.fmean([colour_seconds, background_seconds]):.1f} steps/s including loading and saving, "
          f"{gaussians:,} Gaussians at the end")  # fmt: skip
    shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
