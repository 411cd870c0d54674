"""How far a workspace's training poses put the body's joints from a synthetic subject's true ones (docs/body-fit.md).

    python -m benchmarks.posed_joints WS SAMPLE/train

WS is a workspace trained on SAMPLE/train or on a copy of it with estimated poses (`benchmarks.study.noisy_video`);
SAMPLE/train holds the subject's own body (subject.json) and exact poses. The workspace's joints are its fitted
body's, posed by the poses it trained on (offset and refined, as every later stage uses them).

Prints, per group of joints, the mean distance (cm) from the true joints over the joints and the training frames,
and the same with the mean shift over all joints and frames taken out (what moves from frame to frame and what
the fitted skeleton's proportions add). Then that shift (world axes, cm) and what makes it up at the pelvis,
whose posed position is its rest position plus the frame's translation: the fitted rest pelvis against the
subject's, the workspace's translation offset, the given translations' mean error and the mean of what the pose
fits and GART's refinement added to them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from avatarperfect_cli.body import load_body_template
from avatarperfect_cli.datasets import load_people_snapshot
from avatarperfect_cli.datasets.people_snapshot import FrameRange
from avatarperfect_cli.io.workspace import open_workspace
from avatarperfect_cli.stages.workspace_data import body_template, load_video, transl_offset
from benchmarks.own_video import JOINT_GROUPS, given_poses, world_joints


def joint_errors(workspace: Path, sample_train: Path) -> dict[str, dict[str, float] | torch.Tensor]:
    """Per group of JOINT_GROUPS: {"total", "less shift"} mean distances (cm); "shift": (3,) cm, world axes, and
    "pelvis": its parts, each (3,) cm ("rest pelvis", "offset", "given translations", "fits and refinement")."""
    opened = open_workspace(workspace)
    frames = opened.manifest.get("frames")
    frame_range = None if frames is None else FrameRange(**frames)
    trained = load_video(opened, with_images=False)
    given = given_poses(opened.dataset(), opened, frame_range)
    truth = load_people_snapshot(sample_train, frame_range, with_images=False)
    if not torch.equal(truth.frame_ids, trained.frame_ids):
        raise SystemExit(f"{sample_train} does not hold the frames {workspace} trained on")
    true_rest = load_body_template("anny", phenotype=truth.subject["phenotype"]).rest_joints.float()
    fitted_rest = body_template(opened, opened.manifest["body_model"]).rest_joints.float()
    errors = (world_joints(trained, fitted_rest) - world_joints(truth, true_rest)) * 100.0  # (T, 24, 3) cm
    shift = errors.reshape(-1, 3).mean(dim=0)
    groups = {
        name: {"total": errors[:, joints].norm(dim=-1).mean().item(), "less shift": (errors - shift)[:, joints].norm(dim=-1).mean().item()}
        for name, joints in JOINT_GROUPS.items()
    }
    offset = transl_offset(opened).float()
    pelvis = {
        "rest pelvis": (fitted_rest[0] - true_rest[0]) * 100.0,
        "offset": offset * 100.0,
        "given translations": (given.transl - offset - truth.transl).mean(dim=0) * 100.0,
        "fits and refinement": (trained.transl - given.transl).mean(dim=0) * 100.0,
    }
    return {**groups, "shift": shift, "pelvis": pelvis}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("workspace", type=Path)
    parser.add_argument("sample_train", type=Path)
    args = parser.parse_args()
    result = joint_errors(args.workspace, args.sample_train)
    print("| joints | from the truth (cm) | less the mean shift (cm) |\n|---|---:|---:|")
    for name in JOINT_GROUPS:
        print(f"| {name} | {result[name]['total']:.2f} | {result[name]['less shift']:.2f} |")

    def xyz(vector: torch.Tensor) -> str:
        return ", ".join(f"{value:+.2f}" for value in vector.tolist())

    print(f"\nmean shift of all joints (world x, y, z; cm): {xyz(result['shift'])}")
    parts = result["pelvis"]
    print(f"at the pelvis, {xyz(sum(parts.values()))} cm, of which:")
    for name, vector in parts.items():
        print(f"  {name}: {xyz(vector)}")


if __name__ == "__main__":
    main()
