"""What the masks of a turn-around decide about the body: the body fit from its default starts (what
`train-initial --body-shape fit` does), from the subject's own phenotype, and with the subject's own
phenotype held (only the skeleton correction and the offset fitted), on a synthetic sample whose truth is
known (docs/body-fit.md).

    python -m benchmarks.body_fit_starts SAMPLE/train [--phenotype-prior PX] [--points N] [--poses]

SAMPLE/train is a `make-sample` training folder (its subject.json names the phenotype). Prints one row per
start: the fitted phenotype, the silhouette distance to the masks and the phenotype prior (pixels, the two
terms the fit trades), the fitted rest joints' mean distance from the subject's, and how far the posed
hips and knees sit above (+) or below (-) the subject's, in the world, centimetres (left and right averaged).
Then the loss each default start was compared by (`BodyFit.start_losses`). `--each-start` adds a row per
default start continued alone through the whole fit: what keeping another start would have given. `--poses`
fits every frame's pose with the body, as `train-initial --refine-poses` does for estimated poses (a folder
such as the study's `train-noisy`; its subject.json is the sample's), and the starts are compared with their
poses corrected.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import torch

from avatarperfect_cli.body.anny_model import PHENOTYPES, anny_shape, build_anny_template, default_cache_dir, load_anny_model
from avatarperfect_cli.body.base import joint_displacements
from avatarperfect_cli.datasets import load_people_snapshot
from avatarperfect_cli.training.body_fit import BodyFitConfig, fit_body
from avatarperfect_cli.training.pose_fit import PoseFitConfig
from avatarperfect_cli.training.template_offset import fit_transl_offset

HIPS, KNEES = (1, 2), (4, 5)


def rest_joints(model: object, phenotype: dict[str, float]) -> torch.Tensor:
    """(24, 3) anny's rest joints for `phenotype`, metres."""
    with torch.no_grad():
        return anny_shape(model, torch.tensor([phenotype[name] for name in PHENOTYPES], dtype=torch.float64))[1].float()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("train", type=Path)
    parser.add_argument("--phenotype-prior", type=float, default=BodyFitConfig.phenotype_prior, help="BodyFitConfig.phenotype_prior, pixels")
    parser.add_argument("--points", type=int, default=BodyFitConfig.points, help="template points compared (BodyFitConfig.points)")
    parser.add_argument("--poses", action="store_true", help="fit every frame's pose with the body (estimated poses)")
    parser.add_argument("--each-start", action="store_true", help="also each default start continued alone through the whole fit")
    args = parser.parse_args()
    video = load_people_snapshot(args.train)
    truth = json.loads((args.train / "subject.json").read_text())["phenotype"]
    model = load_anny_model(default_cache_dir(), progress=False)
    middle = {name: 0.5 for name in PHENOTYPES}
    true_joints = rest_joints(model, truth)
    # A start at the subject's own body lands on the masks with no offset: the fit's offset follows the rest
    # root from anny's middle body's, so the initial offset is the two roots' difference.
    own_offset = true_joints[0] - rest_joints(model, middle)[0]
    default = BodyFitConfig(phenotype_prior=args.phenotype_prior, points=args.points)
    starts = {
        "the default starts": (fit_transl_offset(build_anny_template(model, middle), video).offset, default),
        "the subject's own, free": (own_offset, replace(default, starts=(truth,))),
        "the subject's own, held": (own_offset, replace(default, starts=(truth,), start_steps=1, phenotype_rate=0.0)),
    }
    if args.each_start:
        for start in default.starts:
            label = ", ".join(f"{key} {value}" for key, value in start.items()) or "the middle"
            starts[f"start {label} alone"] = (starts["the default starts"][0], replace(default, starts=(start,)))
    print(f"subject: {', '.join(f'{name} {truth[name]:.2f}' for name in PHENOTYPES)}")
    print(f"| start | fitted {', '.join(PHENOTYPES)} | silhouette (px) | prior (px) | rest joints | hips | knees |")
    print("|---|---|---|---|---|---|---|")
    compared = ()
    for name, (initial_offset, config) in starts.items():
        fit = fit_body(video, initial_offset, config, anny_model=model, poses=PoseFitConfig() if args.poses else None)
        compared = compared or fit.start_losses
        joints = rest_joints(model, fit.phenotype) + joint_displacements(fit.bone_offsets)
        height = (joints + fit.transl_offset - true_joints)[:, 1] * 100
        values = torch.tensor([fit.phenotype[key] for key in PHENOTYPES])
        prior = default.phenotype_prior * float(((values - 0.5) / 0.5).square().sum())
        print(
            f"| {name} | {', '.join(f'{fit.phenotype[key]:.2f}' for key in PHENOTYPES)} | {fit.loss:.4f} | {prior:.4f} "
            f"| {(joints - true_joints).norm(dim=-1).mean() * 100:.2f} cm | {height[list(HIPS)].mean():+.2f} cm "
            f"| {height[list(KNEES)].mean():+.2f} cm |"
        )
    print(f"the default starts ({len(compared)}) compared at {', '.join(f'{loss:.4f}' for loss in compared)} px")


if __name__ == "__main__":
    main()
