"""Avatar quality on the synthetic sample: metrics on training and held-out frames, and close-ups of
the artifacts the refinement loop has to repair.

    python -m benchmarks.quality [--sample DIR] [--workspace DIR] [--figure docs/images/artifacts.png]

Without --sample it makes the 512² sample; without --workspace it runs train-initial (2000
iterations). It prints a table of IoU / PSNR / SSIM and writes a figure: for the held-out frames
with the largest local error, crops of ground truth | render | error x4 around that error.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.datasets import load_people_snapshot
from avatarperfect_cli.io import write_image
from avatarperfect_cli.io.workspace import open_workspace
from avatarperfect_cli.sample.generate import make_sample
from avatarperfect_cli.stages.evaluate import comparison_grid, evaluate
from avatarperfect_cli.stages.train_initial import InitialFit, train_initial

CROP = 96
FRAMES_SHOWN = 4


def worst_crops(workspace: Path, test: Path) -> torch.Tensor:
    """Crops (ground truth | render | error) around the largest local error of the worst frames."""
    avatar = Avatar.load(open_workspace(workspace).require_avatar())
    video = load_people_snapshot(test)
    candidates = []
    with torch.no_grad():
        for t in range(len(video)):
            render = render_avatar(avatar, video.body_pose[t], video.transl[t], video.camera, torch.ones(3)).image.clamp(0, 1)
            error = (render - video.images[t]).abs().sum(-1)
            local = torch.nn.functional.avg_pool2d(error[None, None], 15, stride=1, padding=7)[0, 0]
            peak = int(local.argmax())
            candidates.append((float(local.max()), t, divmod(peak, local.shape[1]), render))
    rows = []
    for _, t, (y, x), render in sorted(candidates, reverse=True)[:FRAMES_SHOWN]:
        height, width = render.shape[:2]
        top = min(max(y - CROP // 2, 0), height - CROP)
        left = min(max(x - CROP // 2, 0), width - CROP)
        window = (slice(top, top + CROP), slice(left, left + CROP))
        rows.append((video.images[t][window], render[window]))
    grid = comparison_grid(rows)
    return grid.repeat_interleave(2, dim=0).repeat_interleave(2, dim=1)  # 2x, nearest, for reading


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sample", type=Path)
    parser.add_argument("--workspace", type=Path)
    parser.add_argument("--figure", type=Path, default=Path("docs/images/artifacts.png"))
    args = parser.parse_args()
    scratch = Path(tempfile.mkdtemp())
    if args.sample is None:
        args.sample = scratch / "sample"
        make_sample(args.sample)
    if args.workspace is None:
        args.workspace = scratch / "ws"
        train_initial(args.sample / "train", args.workspace, InitialFit())
    print("| video | frames | IoU | PSNR (dB) | SSIM |\n|---|---:|---:|---:|---:|")
    for split in ("train", "test"):
        result = evaluate(args.workspace, args.sample / split, progress=False)
        mean = result["mean"]
        print(f"| {split} | {result['frames']} | {mean['iou']:.4f} | {mean['psnr']:.2f} | {mean['ssim']:.4f} |")
    write_image(args.figure, worst_crops(args.workspace, args.sample / "test"))
    print(f"\nartifact close-ups: {args.figure}")


if __name__ == "__main__":
    main()
