"""A finished study's avatars scored with their test poses refined, beside the exact test poses.

    python -m benchmarks.study_refined OUT [--presets default female tall] [--seeds 0 1]
                                           [--conditions initial ap-exact random canonical] [--pictured]

OUT: a `benchmarks/study.py` folder (OUT/PRESET/sample, OUT/PRESET/seed-S/CONDITION). Each condition's final
avatar is scored on the held-out video twice, as `evaluate --refine-poses` does: with the exact test poses
(moved by the workspace's offset, what study.py reports), and with each test pose fitted to its frame's mask
and image with the avatar fixed (`evaluate.refined_test_poses`), the protocol of InstantAvatar and
3DGS-Avatar. With a fitted body, the exact poses put the avatar's outline a pixel or two off the truth in
every held-out frame; the refined poses remove that, so the second score measures the avatar's look.
Hidden-region PSNR uses the truth's texture regions, so it is comparable between the two. Prints a table
of held-out and hidden-region PSNR and their change from the initial avatar, per subject and seed and as
the mean; writes OUT/study-refined-seeds-S.json (S: the seeds, joined by "-"). About 2 minutes per avatar at 512² on 2 cores.

--pictured also scores, per subject and seed, what the simulated user pictures (the subject's own mesh with
its joints where the avatar's skeleton puts them, `pictured_truth`) in place of the avatar, at the same test
poses: the score of an avatar that looks exactly as the user paints it.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from dataclasses import replace
from pathlib import Path

import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.datasets import load_people_snapshot
from avatarperfect_cli.io.pose_json import PoseFile
from avatarperfect_cli.io.workspace import open_workspace
from avatarperfect_cli.sample.simulated_user import pictured_truth
from avatarperfect_cli.sample.subject import SyntheticSubject
from avatarperfect_cli.stages.evaluate import refined_test_poses
from avatarperfect_cli.stages.workspace_data import transl_offset
from avatarperfect_cli.training import metrics
from benchmarks.study import HeldOut, held_out, score

SCORES = (("psnr", "PSNR"), ("psnr_hidden", "hidden"), ("iou", "IoU"))


def refined_scores(avatar: Avatar, sample: Path, offset: torch.Tensor, data: HeldOut) -> tuple[dict, dict, HeldOut]:
    """The study's metrics of `avatar` with the exact test poses (moved by `offset`) and with them refined, and
    the held-out data with the refined poses."""
    exact, _ = score(avatar, data, offset)
    test = load_people_snapshot(sample / "test", downscale=1)
    test.transl = test.transl + offset
    body_pose, transl = refined_test_poses(avatar, test, progress=False)
    refined_data = replace(data, poses=[PoseFile(body_pose[t], transl[t], test.camera) for t in range(len(test))])
    refined, _ = score(avatar, refined_data, torch.zeros(3))
    return exact, refined, refined_data


def pictured_scores(subject: SyntheticSubject, rest_joints: torch.Tensor, data: HeldOut, offset: torch.Tensor) -> dict:
    """Held-out IoU and PSNR (means over frames) and hidden-region PSNR (over all frames' pixels together, as
    `score`) of the subject as the user pictures it (`pictured_truth`: joints where an avatar on `rest_joints`
    (24, 3) puts them) at the poses of `data`, their translations moved by `offset` (3,) metres."""
    rows, squared_error, values = [], 0.0, 0
    for t, pose in enumerate(data.poses):
        moved = PoseFile(pose.body_pose, pose.transl + offset, pose.camera)
        pictured = pictured_truth(subject, moved, rest_joints, offset, "avatar")
        render, hidden = torch.from_numpy(pictured.rgb), data.hidden(t)
        rows.append((metrics.iou(torch.from_numpy(pictured.coverage) >= 0.5, data.masks[t]), metrics.psnr(render, data.images[t])))
        squared_error += float(((render.double() - data.images[t].double()) ** 2)[hidden].sum())
        values += int(hidden.sum()) * 3
    return {
        "iou": statistics.fmean(iou for iou, _ in rows), "psnr": statistics.fmean(psnr for _, psnr in rows),
        "psnr_hidden": -10 * math.log10(squared_error / values),
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path)
    parser.add_argument("--presets", nargs="+", default=["default", "female", "tall"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--conditions", nargs="+", default=["initial", "ap-exact", "random", "canonical"])
    parser.add_argument("--pictured", action="store_true", help="also score what the simulated user pictures")
    args = parser.parse_args()
    if "initial" not in args.conditions:
        args.conditions.insert(0, "initial")  # the gains are measured from it
    results: dict[str, dict[str, dict[str, dict]]] = {}
    record = args.out / f"study-refined-seeds-{'-'.join(map(str, args.seeds))}.json"
    for preset in args.presets:
        sample = args.out / preset / "sample"
        data = held_out(sample, 1)
        subject = SyntheticSubject.from_dataset(sample / "test")
        for seed in args.seeds:
            key = f"{preset} seed {seed}"
            results[key] = {}
            for condition in args.conditions:
                workspace = open_workspace(args.out / preset / f"seed-{seed}" / condition)
                avatar = Avatar.load(workspace.require_avatar())
                start = time.perf_counter()
                offset = transl_offset(workspace)
                exact, refined, refined_data = refined_scores(avatar, sample, offset, data)
                results[key][condition] = {"exact": exact, "refined": refined}
                if args.pictured and condition == "initial":
                    pictured = {
                        "exact": pictured_scores(subject, avatar.rest_joints, data, offset),
                        "refined": pictured_scores(subject, avatar.rest_joints, refined_data, torch.zeros(3)),
                    }  # fmt: skip
                    results[key]["pictured"] = pictured
                    print(f"{key} pictured: PSNR {pictured['exact']['psnr']:.2f} -> {pictured['refined']['psnr']:.2f} dB refined, "
                          f"hidden {pictured['exact']['psnr_hidden']:.2f} -> {pictured['refined']['psnr_hidden']:.2f} dB", flush=True)  # fmt: skip
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
