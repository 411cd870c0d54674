"""A paint that contradicts the video: a flat square on the torso at a held-out pose, refined at each strength.

    python -m benchmarks.edit_strength WORKSPACE SAMPLE_DIR [--frame 19] [--colour 1,0,1] [--images docs/images]

WORKSPACE: a workspace trained on SAMPLE_DIR/train (after train-initial). On a copy per strength, the avatar
is rendered in held-out frame --frame of SAMPLE_DIR/test, a square (a sixteenth of the image side) of
--colour is painted over the torso (the middle of the spine, projected), the painting is registered with
`apply-edit --pose` at that strength, and one refine runs. Prints the PSNR inside the square against the
paint before and after, the share of the way refine reports, and the training frames' PSNR; writes
painted | default | strong to --images.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.body import forward_kinematics
from avatarperfect_cli.datasets import load_people_snapshot
from avatarperfect_cli.io import PoseFile, write_image, write_pose
from avatarperfect_cli.io.workspace import open_workspace
from avatarperfect_cli.refinement.pictures import caption_strip
from avatarperfect_cli.stages.apply_edit import apply_edit
from avatarperfect_cli.stages.refine import refine
from avatarperfect_cli.stages.workspace_data import transl_offset
from benchmarks.refine import training_psnr

WHITE = torch.ones(3)
SPINE = 6  # SMPL's spine2: the middle of the torso
STRENGTHS = ("default", "strong")


def held_out_pose(ws: Path, sample: Path, frame: int) -> PoseFile:
    test = load_people_snapshot(sample / "test", split="test", with_images=False)
    workspace = open_workspace(ws)
    return PoseFile(test.body_pose[frame], test.transl[frame] + transl_offset(workspace), test.camera)


def render(ws: Path, pose: PoseFile) -> torch.Tensor:
    avatar = Avatar.load(open_workspace(ws).require_avatar())
    with torch.no_grad():
        return render_avatar(avatar, pose.body_pose, pose.transl, pose.camera, WHITE).image.clamp(0, 1)


def painted_square(ws: Path, pose: PoseFile, colour: tuple[float, float, float]) -> tuple[torch.Tensor, torch.Tensor]:
    """(the render with the square painted (H, W, 3), the square (H, W) bool)."""
    image = torch.round(render(ws, pose) * 255) / 255
    avatar = Avatar.load(open_workspace(ws).require_avatar())
    transform = forward_kinematics(pose.body_pose[None], avatar.rest_joints, pose.transl[None])[0, SPINE]
    spine = transform[:3, :3] @ avatar.rest_joints[SPINE] + transform[:3, 3]  # the joint, posed
    camera = pose.camera
    point = camera.K @ (camera.world_to_camera[:3, :3] @ spine + camera.world_to_camera[:3, 3])
    column, row = (point[:2] / point[2]).round().long().tolist()
    half = max(2, camera.width // 32)
    square = torch.zeros(image.shape[:2], dtype=torch.bool)
    square[row - half : row + half, column - half : column + half] = True
    painted = image.clone()
    painted[square] = torch.tensor(colour)
    return painted, square


def masked_psnr(image: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> float:
    error = ((image - target) ** 2)[mask].mean()
    return float(-10.0 * torch.log10(error))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("workspace", type=Path)
    parser.add_argument("sample", type=Path)
    parser.add_argument("--frame", type=int, default=19, help="held-out frame of SAMPLE/test")
    parser.add_argument("--colour", default="1,0,1", help="the square's colour, R,G,B in [0, 1]")
    parser.add_argument("--iterations", type=int, default=500)
    parser.add_argument("--strengths", default=",".join(STRENGTHS), help="which strengths to run, comma-separated")
    parser.add_argument("--images", type=Path)
    args = parser.parse_args()
    colour = tuple(float(value) for value in args.colour.split(","))
    pose = held_out_pose(args.workspace, args.sample, args.frame)
    painted, square = painted_square(args.workspace, pose, colour)
    before = masked_psnr(render(args.workspace, pose), painted, square)
    training_before = training_psnr(Avatar.load(open_workspace(args.workspace).require_avatar()), args.workspace)
    results = {}
    with tempfile.TemporaryDirectory() as scratch:
        write_image(Path(scratch) / "painted.png", painted)
        write_pose(Path(scratch) / "pose.json", pose)
        for strength in args.strengths.split(","):
            ws = Path(scratch) / strength
            shutil.copytree(args.workspace, ws)
            apply_edit(ws, Path(scratch) / "painted.png", Path(scratch) / "pose.json", strength=strength, progress=False)
            start = time.perf_counter()
            refine(ws, progress=True)
            seconds = time.perf_counter() - start
            history = open_workspace(ws).manifest["history"][-1]
            after = render(ws, pose)
            results[strength] = after
            training = training_psnr(Avatar.load(open_workspace(ws).require_avatar()), ws)
            print(
                f"{strength}: inside the square {before:.2f} -> {masked_psnr(after, painted, square):.2f} dB "
                f"(+{masked_psnr(after, painted, square) - before:.2f}), reported share {json.dumps(history['edit_progress'])}, "
                f"training frames {training_before:.2f} -> {training:.2f} dB, refine {seconds:.1f} s"
            )
    if args.images and set(results) == set(STRENGTHS):
        labels = ["painted (held-out pose)", "after refine: default", "after refine: strong"]
        row = torch.cat([painted, results["default"], results["strong"]], dim=1)
        write_image(args.images / "refine_edit_strength.png", torch.cat([caption_strip(labels, painted.shape[1]), row]))


if __name__ == "__main__":
    main()
