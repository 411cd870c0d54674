"""Mask error and streaks: `train-initial` on a sample's exact, dilated and eroded training masks, scored on
its exact held-out frames, with the share of long Gaussians (docs/avatar-quality.md).

    python -m benchmarks.mask_error SAMPLE OUT [--pixels 3] [--conditions exact,dilated,eroded]

SAMPLE is a `make-sample` folder (SAMPLE/train, SAMPLE/test). For a dilated or eroded condition,
OUT/<condition>/train is a copy of SAMPLE/train whose masks are dilated or eroded by --pixels (cv2, an
elliptical kernel); the exact condition trains on SAMPLE/train itself. Each trains OUT/<condition>/ws with
`train-initial --body-shape exact` (the subject's own body, so the figures measure the masks) and
`evaluate`s it on SAMPLE/test. Prints one table row per condition: held-out IoU, PSNR, SSIM, the Gaussian
count and the shares of Gaussians whose largest standard deviation exceeds 3 and 6 cm.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

from avatarperfect_cli.io.ply import read_gaussians
from avatarperfect_cli.io.workspace import open_workspace

LENGTHS = (0.03, 0.06)  # metres


def perturbed_copy(train: Path, out: Path, pixels: int) -> Path:
    """Copy the training folder `train` to `out` with its masks (masks/*.npy 0/1, or *.png 0/255) dilated
    (pixels > 0) or eroded (pixels < 0) by |pixels|; returns `out`."""
    shutil.copytree(train, out)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * abs(pixels) + 1,) * 2)
    change = cv2.dilate if pixels > 0 else cv2.erode
    for path in sorted((out / "masks").iterdir()):
        if path.suffix == ".npy":
            np.save(path, change(np.load(path).astype(np.uint8), kernel))
        elif path.suffix == ".png":
            cv2.imwrite(str(path), change(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE), kernel))
    return out


def long_shares(ply: Path) -> tuple[int, list[float]]:
    """The avatar's Gaussian count and the shares of them whose largest standard deviation exceeds each of
    LENGTHS."""
    largest = torch.exp(read_gaussians(ply).log_scales).amax(dim=-1)
    return len(largest), [float((largest > length).float().mean()) for length in LENGTHS]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sample", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--pixels", type=int, default=3)
    parser.add_argument("--conditions", default="exact,dilated,eroded")
    args = parser.parse_args()
    shifts = {"exact": 0, "dilated": args.pixels, "eroded": -args.pixels}
    print("| masks | IoU | PSNR (dB) | SSIM | Gaussians | > 3 cm | > 6 cm |\n|---|---:|---:|---:|---:|---:|---:|")
    for condition in args.conditions.split(","):
        folder = args.out / condition
        folder.mkdir(parents=True, exist_ok=True)
        train = args.sample / "train"
        if shifts[condition]:
            train = folder / "train" if (folder / "train").is_dir() else perturbed_copy(train, folder / "train", shifts[condition])
        cli = [sys.executable, "-m", "avatarperfect_cli"]
        subprocess.run([*cli, "train-initial", str(train), str(folder / "ws"), "--body-shape", "exact", "--force"], check=True)
        subprocess.run([*cli, "evaluate", str(folder / "ws"), "--test", str(args.sample / "test")], check=True)
        metrics = json.loads(max((folder / "ws" / "eval").glob("*/metrics.json")).read_text())["mean"]
        count, shares = long_shares(open_workspace(folder / "ws").require_avatar())
        print(
            f"| {condition} | {metrics['iou']:.3f} | {metrics['psnr']:.2f} | {metrics['ssim']:.4f} | {count:,} | "
            f"{100 * shares[0]:.2f} % | {100 * shares[1]:.2f} % |",
            flush=True,
        )


if __name__ == "__main__":
    main()
