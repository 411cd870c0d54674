"""Real data as other tools write it, built from the committed 256² sample: an InstantAvatar folder (split
files in the camera's y-down frame, no poses.npz, no subject.json) and SMPL-like translations that put the
template 0.4 m off the subject. Short trainings at 64² (60 steps, 10 frames)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from avatarperfect_cli.body import axis_angle_to_matrix, load_body_template
from avatarperfect_cli.cli import app
from avatarperfect_cli.datasets import load_people_snapshot
from avatarperfect_cli.io.workspace import open_workspace
from avatarperfect_cli.rotations import matrix_to_axis_angle
from avatarperfect_cli.stages.workspace_data import load_video

SAMPLE = Path(__file__).resolve().parents[2] / "examples" / "sample" / "train"
FAST = ["--iterations", "60", "--resolution", "64"]
TRAIN_FRAMES, TEST_FRAMES = np.arange(0, 40, 2), np.arange(40, 60, 2)  # 20 + 10 rows for 60 images: step 2


def invoke(*args: object):
    return CliRunner().invoke(app, [str(a) for a in args])


def mean_iou(workspace: Path, test: Path, *args: str) -> dict:
    result = invoke("evaluate", workspace, "--test", test, *args)
    assert result.exit_code == 0, result.output
    return json.loads((workspace / "eval" / "000" / test.name / "metrics.json").read_text())


@pytest.fixture(scope="module")
def instantavatar_folder(tmp_path_factory) -> Path:
    """The sample as InstantAvatar stores People-Snapshot: cameras.npz with the identity extrinsic (the world
    is the camera's frame), poses/anim_nerf_{train,test}.npz (betas (1, 10), global_orient, body_pose (N, 69),
    transl) whose rows follow their split's frames, images and masks of every frame."""
    root = tmp_path_factory.mktemp("instantavatar") / "subject"
    root.mkdir()
    shutil.copytree(SAMPLE / "images", root / "images")
    shutil.copytree(SAMPLE / "masks", root / "masks")
    with np.load(SAMPLE / "cameras.npz") as camera:
        extrinsic = torch.from_numpy(camera["extrinsic"])
        size = {"height": camera["height"], "width": camera["width"]}
        np.savez(root / "cameras.npz", intrinsic=camera["intrinsic"], extrinsic=np.eye(4), **size)
    video = load_people_snapshot(SAMPLE, with_images=False)
    rest_pelvis = load_body_template("anny", phenotype=video.subject["phenotype"]).rest_joints[0].double()
    rotation, shift = extrinsic[:3, :3], extrinsic[:3, 3]
    body_pose = video.body_pose.double()
    body_pose[:, 0] = matrix_to_axis_angle(rotation @ axis_angle_to_matrix(body_pose[:, 0]))
    transl = (rest_pelvis + video.transl.double()) @ rotation.T + shift - rest_pelvis  # the roots move with the world
    (root / "poses").mkdir()
    for split, frames in (("train", TRAIN_FRAMES), ("test", TEST_FRAMES)):
        thetas = body_pose[frames].reshape(-1, 72).numpy()
        np.savez(
            root / "poses" / f"anim_nerf_{split}.npz",
            betas=np.zeros((1, 10), np.float32), global_orient=thetas[:, :3].astype(np.float32),
            body_pose=thetas[:, 3:].astype(np.float32), transl=transl[frames].numpy().astype(np.float32),
        )  # fmt: skip
    return root


def test_an_instantavatar_folder_trains_and_evaluates_with_no_extra_flags(instantavatar_folder: Path, tmp_path: Path):
    result = invoke("train-initial", instantavatar_folder, tmp_path / "ws", *FAST)
    assert result.exit_code == 0, result.output
    assert "assuming frames 0..38 step 2" in result.stderr and "template offset" in result.stderr
    workspace = open_workspace(tmp_path / "ws")
    assert workspace.manifest["poses"] == "poses/anim_nerf_train.npz"
    offset = torch.tensor(workspace.manifest["transl_offset"])
    # no subject.json: the body is fitted to the masks, and the fitted body's pelvis lands where the sample's
    # does (anny's middle body would need about 5 cm more)
    assert "body fitted to the masks" in result.stderr
    assert set(workspace.manifest["body_model"]["phenotype"]) == {"gender", "age", "muscle", "weight", "height", "proportions"}
    assert float(offset.norm()) < 0.03

    # visibility / refine re-load the video from the manifest: the same frames, poses and offset.
    video = load_video(workspace, with_images=False)
    assert video.frame_ids.tolist() == TRAIN_FRAMES.tolist()
    with np.load(instantavatar_folder / "poses" / "anim_nerf_train.npz") as split:
        torch.testing.assert_close(video.transl, torch.from_numpy(split["transl"]) + offset)

    metrics = mean_iou(tmp_path / "ws", instantavatar_folder)
    assert metrics["poses"] == "poses/anim_nerf_test.npz"
    assert [frame["frame"] for frame in metrics["per_frame"]] == TEST_FRAMES.tolist()
    assert metrics["mean"]["iou"] > 0.6


def test_a_known_offset_is_recovered_and_trains_like_no_offset(tmp_path: Path):
    """SMPL-like translations 0.4 m below the template's: recovered within 2 cm, and the avatar's IoU on its
    training frames within 0.01 of the same training on the unmoved sample."""
    moved = tmp_path / "moved"
    shutil.copytree(SAMPLE, moved)
    with np.load(SAMPLE / "poses.npz") as poses:
        contents = dict(poses)
    contents["transl"] = contents["transl"] - np.array([0.0, 0.4, 0.0], np.float32)
    np.savez(moved / "poses.npz", **contents)
    frames = ["--frames", "0:59:6"]
    for folder, workspace, extra in ((SAMPLE, "reference", []), (moved, "fitted", ["--transl-offset", "fit"])):
        result = invoke("train-initial", folder, tmp_path / workspace, *FAST, *frames, *extra)
        assert result.exit_code == 0, result.output
    offset = torch.tensor(open_workspace(tmp_path / "fitted").manifest["transl_offset"])
    assert float((offset - torch.tensor([0.0, 0.4, 0.0])).norm()) < 0.02, offset
    assert open_workspace(tmp_path / "reference").manifest["transl_offset"] == [0.0, 0.0, 0.0]
    reference = mean_iou(tmp_path / "reference", SAMPLE, *frames)["mean"]["iou"]
    fitted = mean_iou(tmp_path / "fitted", moved, *frames)["mean"]["iou"]
    assert reference > 0.5 and abs(fitted - reference) <= 0.01, (reference, fitted)


def test_a_malformed_transl_offset_is_one_line(tmp_path: Path):
    result = invoke("train-initial", SAMPLE, tmp_path / "ws", "--transl-offset", "0.1,0.2")
    assert result.exit_code == 2 and result.stderr.strip().splitlines() == [
        "error: --transl-offset '0.1,0.2' is not auto, fit, off or X,Y,Z in metres"
    ]
    assert not (tmp_path / "ws").exists()
