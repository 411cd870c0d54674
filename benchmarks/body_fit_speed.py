"""How long the body fit takes (`train-initial --body-shape fit`'s fit, before any Gaussian is trained).

    python -m benchmarks.body_fit_speed FOLDER [FOLDER ...] [--poses] [--repeats 3]

FOLDER is a People-Snapshot training folder (a `make-sample` train folder, or the study's train-noisy).
Runs the fit from anny's default starts once per folder, then `--repeats` more times in the same process, and
prints one row per folder: the first run's wall time, the median of the repeats, and the final silhouette
distance. Give one folder per process for a first run like `train-initial`'s, in a new process. `--poses`
fits every frame's pose with the body, as for estimated poses.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from avatarperfect_cli.body.anny_model import PHENOTYPES, build_anny_template, default_cache_dir, load_anny_model
from avatarperfect_cli.datasets import load_people_snapshot
from avatarperfect_cli.training.body_fit import BodyFitConfig, fit_body
from avatarperfect_cli.training.pose_fit import PoseFitConfig
from avatarperfect_cli.training.template_offset import fit_transl_offset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", type=Path, nargs="+")
    parser.add_argument("--poses", action="store_true", help="fit every frame's pose with the body (estimated poses)")
    parser.add_argument("--repeats", type=int, default=3, help="runs after the first")
    args = parser.parse_args()
    model = load_anny_model(default_cache_dir(), progress=False)
    middle = build_anny_template(model, {name: 0.5 for name in PHENOTYPES})
    print("| folder | frames | poses fitted | first run (s) | median of the repeats (s) | silhouette distance (px) |\n|---|---:|---|---:|---:|---:|")
    for folder in args.folders:
        video = load_people_snapshot(folder)
        offset = fit_transl_offset(middle, video).offset
        seconds, loss = [], 0.0
        for _ in range(1 + args.repeats):
            start = time.perf_counter()
            loss = fit_body(video, offset, BodyFitConfig(), anny_model=model, poses=PoseFitConfig() if args.poses else None).loss
            seconds.append(time.perf_counter() - start)
        repeats = f"{statistics.median(seconds[1:]):.1f}" if args.repeats else "–"
        print(f"| {folder} | {len(video)} | {'yes' if args.poses else 'no'} | {seconds[0]:.1f} | {repeats} | {loss:.4f} |")


if __name__ == "__main__":
    main()
