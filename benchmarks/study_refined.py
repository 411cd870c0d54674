"""A finished study's avatars scored with their test poses refined, beside the exact test poses.

    python -m benchmarks.study_refined OUT [--presets default female tall] [--seeds 0 1]
                                           [--conditions initial ap-exact random canonical]

OUT: a `benchmarks/study.py` folder (OUT/PRESET/sample, OUT/PRESET/seed-S/CONDITION). Each condition's final
avatar is scored on the held-out video twice, as `evaluate --refine-poses` does: with the exact test poses
(moved by the workspace's offset, what study.py reports), and with each test pose fitted to its frame's mask
and image with the avatar fixed (`evaluate.refined_test_poses`), the protocol of InstantAvatar and
3DGS-Avatar. With a fitted body, the exact poses put the avatar's outline a pixel or two off the truth in
every held-out frame; the refined poses remove that, so the second score measures the avatar's look.
Hidden-region PSNR uses the truth's texture regions, so it is comparable between the two. Prints a table
of held-out and hidden-region PSNR and their change from the initial avatar, per subject and seed and as
the mean; writes OUT/study-refined-seeds-S.json (S: the seeds, joined by "-"). About 2 minutes per avatar at 512² on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from dataclasses import replace
from pathlib import Path

import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.datasets import load_people_snapshot
from avatarperfect_cli.io.pose_json import PoseFile
from avatarperfect_cli.io.workspace import open_workspace
from avatarperfect_cli.stages.evaluate import refined_test_poses
from avatarperfect_cli.stages.workspace_data import transl_offset
from benchmarks.study import held_out, score

SCORES = (("psnr", "PSNR"), ("psnr_hidden", "hidden"), ("iou", "IoU"))


def refined_scores(avatar: Avatar, sample: Path, offset: torch.Tensor, data) -> tuple[dict, dict]:
    """The study's metrics of `avatar` with the exact test poses (moved by `offset`) and with them refined."""
    exact, _ = score(avatar, data, offset)
    test = load_people_snapshot(sample / "test", downscale=1)
    test.transl = test.transl + offset
    body_pose, transl = refined_test_poses(avatar, test, progress=False)
    refined_data = replace(data, poses=[PoseFile(body_pose[t], transl[t], test.camera) for t in range(len(test))])
    refined, _ = score(avatar, refined_data, torch.zeros(3))
    return exact, refined


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path)
    parser.add_argument("--presets", nargs="+", default=["default", "female", "tall"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--conditions", nargs="+", default=["initial", "ap-exact", "random", "canonical"])
    args = parser.parse_args()
    if "initial" not in args.conditions:
        args.conditions.insert(0, "initial")  # the gains are measured from it
    results: dict[str, dict[str, dict[str, dict]]] = {}
    record = args.out / f"study-refined-seeds-{'-'.join(map(str, args.seeds))}.json"
    for preset in args.presets:
        sample = args.out / preset / "sample"
        data = held_out(sample, 1)
        for seed in args.seeds:
            key = f"{preset} seed {seed}"
            results[key] = {}
            for condition in args.conditions:
                workspace = open_workspace(args.out / preset / f"seed-{seed}" / condition)
                avatar = Avatar.load(workspace.require_avatar())
                start = time.perf_counter()
                exact, refined = refined_scores(avatar, sample, transl_offset(workspace), data)
                results[key][condition] = {"exact": exact, "refined": refined}
                print(f"{key} {condition}: PSNR {exact['psnr']:.2f} -> {refined['psnr']:.2f} dB refined, hidden "
                      f"{exact['psnr_hidden']:.2f} -> {refined['psnr_hidden']:.2f} dB ({time.perf_counter() - start:.0f} s)",
                      flush=True)  # fmt: skip
                record.write_text(json.dumps(results, indent=2))
    print("\n| subject | condition | " + " | ".join(f"{label} exact | {label} refined" for _, label in SCORES) +
          " | change exact (held out / hidden) | change refined (held out / hidden) |")  # fmt: skip
    print("|---|---|" + "---:|" * (2 * len(SCORES) + 2))
    gains: dict[str, dict[str, list[float]]] = {}
    for key, conditions in results.items():
        initial = conditions["initial"]
        for condition, scored in conditions.items():
            values = " | ".join(f"{scored[kind][name]:.{4 if name == 'iou' else 2}f}" for name, _ in SCORES for kind in ("exact", "refined"))
            change = {kind: [scored[kind][name] - initial[kind][name] for name in ("psnr", "psnr_hidden")] for kind in ("exact", "refined")}
            for kind, (held, hidden) in change.items():
                gains.setdefault(condition, {}).setdefault(kind, []).append((held, hidden))
            print(f"| {key} | {condition} | {values} | {change['exact'][0]:+.2f} / {change['exact'][1]:+.2f} | "
                  f"{change['refined'][0]:+.2f} / {change['refined'][1]:+.2f} |")  # fmt: skip
    print("\n| condition | change, exact test poses (held out / hidden) | change, refined test poses (held out / hidden) |")
    print("|---|---:|---:|")
    for condition, kinds in gains.items():
        cells = [f"{statistics.fmean(h for h, _ in pairs):+.2f} / {statistics.fmean(d for _, d in pairs):+.2f}" for pairs in kinds.values()]
        print(f"| {condition} | {' | '.join(cells)} |")


if __name__ == "__main__":
    main()
