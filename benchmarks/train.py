"""Training speed on the CPU: steps per second at 512² with ~30k Gaussians, and train-initial's wall time.

    python -m benchmarks.train [--steps 40] [--sample DIR] [--iterations 2000]

The step benchmark fits the anny template, doubled to ~27k Gaussians by a jittered copy of each,
to 512² frames of the sample subject: skinning (LBS), rasterization, L1 + SSIM on the subject's box,
backward, Adam (densification off, so the count stays fixed). The second part times `avatarperfect train-initial` on a sample
made with `avatarperfect make-sample` (512², 100 frames), if --sample is given.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.body import load_body_template
from avatarperfect_cli.datasets import load_people_snapshot
from avatarperfect_cli.training.strategy import DensifyConfig
from avatarperfect_cli.training.trainer import TrainConfig, train, video_views

ROOT = Path(__file__).resolve().parents[1]


def doubled(avatar: Avatar) -> Avatar:
    """The avatar with every Gaussian duplicated and jittered by a fraction of its size (2N Gaussians)."""
    params = {}
    for name, value in avatar.params.items():
        params[name] = torch.cat([value.detach(), value.detach()])
    jitter = torch.randn_like(avatar.params["means"]) * avatar.scales.detach() * 0.5
    params["means"][len(avatar) :] += jitter
    return Avatar(params, avatar.rest_joints, avatar.sh_degree, avatar.sh_degree, avatar.body_model)


def step_seconds(sample: Path, steps: int) -> tuple[float, int]:
    """Seconds per training step (the difference of a long and a short run, so start-up cancels)."""
    video = load_people_snapshot(sample)
    template = load_body_template("anny", phenotype=video.subject["phenotype"])
    views = video_views(video)
    runs = {}
    for iterations in (5, 5 + steps):
        avatar = doubled(Avatar.from_template(template))
        config = TrainConfig(iterations=iterations, densify=DensifyConfig(refine_stop=0))
        start = time.perf_counter()
        train(avatar, views, config=config, progress=False)
        runs[iterations] = time.perf_counter() - start
    return (runs[5 + steps] - runs[5]) / steps, len(avatar)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--sample", type=Path, help="a make-sample folder (512²) for the train-initial timing")
    parser.add_argument("--iterations", type=int, default=2000)
    args = parser.parse_args()
    if args.sample is None:
        print("no --sample given: making one (512², 100 + 30 frames)...")
        args.sample = Path(tempfile.mkdtemp()) / "sample"
        subprocess.run([sys.executable, "-m", "avatarperfect_cli", "make-sample", str(args.sample)], check=True)
    step, count = step_seconds(args.sample / "train", args.steps)
    print("| what | value |\n|---|---:|")
    print(f"| training step, 512², {count:,} Gaussians | {1000 * step:.1f} ms = {1 / step:.1f} it/s |")
    with tempfile.TemporaryDirectory() as scratch:
        start = time.perf_counter()
        subprocess.run(
            [sys.executable, "-m", "avatarperfect_cli", "train-initial", str(args.sample / "train"), f"{scratch}/ws", "--iterations", str(args.iterations)],
            check=True,
        )
        wall = time.perf_counter() - start
    print(f"| train-initial, {args.iterations} iterations, wall (Python start included) | {wall:.0f} s |")


if __name__ == "__main__":
    main()
