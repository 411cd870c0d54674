"""How the simulated user judges a suggestion of a fitted-body avatar: pixel by pixel against the subject in
the suggested joint angles, or as a person would (the subject posed where the avatar's skeleton stands, a
displacement of a few pixels overlooked).

    python -m benchmarks.user_judgement OUT FIGURE.png [--seed 0] [--condition ap-exact] [--views default:001 tall:001]

OUT: a finished `benchmarks/study.py` folder. For each PRESET:NNN, suggestion NNN of that subject's condition
workspace, one row at half size: the suggestion; the subject in the suggested joint angles on its own
skeleton and what a pixel-by-pixel user paints against it (`--outline-tolerance 0 --truth-pose suggested`,
black: painted); the
subject posed like the avatar (`SyntheticSubject.render_posed_like`) and what the default user paints.
Prints the painted pixels of each kind.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.io import read_image, read_pose, write_image
from avatarperfect_cli.io.workspace import open_workspace
from avatarperfect_cli.sample.simulated_user import PaintResult, UserConfig, paint, pictured_truth
from avatarperfect_cli.sample.subject import SyntheticSubject
from avatarperfect_cli.stages.workspace_data import transl_offset


def _painted(result: PaintResult) -> torch.Tensor:
    """(H, W, 3) black where the strokes cover the image, white elsewhere."""
    return (1.0 - result.stroke_weight)[..., None].expand(-1, -1, 3)


def judgement_row(out: Path, preset: str, seed: int, condition: str, suggestion: str) -> torch.Tensor:
    """(H, 5 W, 3) the row described in the module docstring, for one suggestion."""
    workspace = open_workspace(out / preset / f"seed-{seed}" / condition)
    subject = SyntheticSubject.from_dataset(out / preset / "sample" / "train")
    folder = workspace.root / "suggestions" / suggestion
    pose = read_pose(folder / "pose.json")
    suggested = read_image(folder / "suggested.png", "RGB")
    alpha = read_image(folder / "suggested_alpha.png", "L")[..., 0]
    rest_joints = Avatar.load(workspace.require_avatar()).rest_joints  # refine keeps the skeleton
    same_angles, posed_like = (pictured_truth(subject, pose, rest_joints, transl_offset(workspace), kind) for kind in ("suggested", "avatar"))
    by_pixel = paint(suggested, alpha, same_angles, UserConfig(outline_tolerance=0.0, truth_pose="suggested"))
    as_person = paint(suggested, alpha, posed_like, UserConfig())
    print(f"{preset} {suggestion}: pixel by pixel {by_pixel.stats.painted_by_kind}, as a person {as_person.stats.painted_by_kind}")
    truths = [torch.from_numpy(render.rgb.astype(np.float32)) for render in (same_angles, posed_like)]
    return torch.cat([suggested, truths[0], _painted(by_pixel), truths[1], _painted(as_person)], dim=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path)
    parser.add_argument("figure", type=Path)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--condition", default="ap-exact")
    parser.add_argument("--views", nargs="+", default=["default:001", "tall:001"], metavar="PRESET:NNN")
    args = parser.parse_args()
    rows = []
    for view in args.views:
        preset, suggestion = view.split(":")
        rows.append(judgement_row(args.out, preset, args.seed, args.condition, suggestion))
    grid = torch.cat(rows, dim=0).permute(2, 0, 1)[None]
    write_image(args.figure, torch.nn.functional.interpolate(grid, scale_factor=0.5, mode="area")[0].permute(1, 2, 0))


if __name__ == "__main__":
    main()
