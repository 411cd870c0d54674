"""train-initial, evaluate and render on the committed 256² sample, shrunk to 64² for speed."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from avatarperfect_cli.cli import app
from avatarperfect_cli.io import read_image
from avatarperfect_cli.io.workspace import open_workspace, workspace_lock
from avatarperfect_cli.stages import train_initial as train_initial_stage

SAMPLE = Path(__file__).resolve().parents[2] / "examples" / "sample"
TRAIN_ARGS = ["--iterations", "40", "--resolution", "64", "--frames", "0:59:6"]


def invoke(*args: str):
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("pipeline") / "ws"
    result = invoke("train-initial", SAMPLE / "train", root, *TRAIN_ARGS)
    assert result.exit_code == 0, result.output
    return root


def test_train_initial_creates_the_workspace(workspace: Path):
    ws = open_workspace(workspace)
    assert ws.iteration == 0 and ws.avatar_path(0).is_file()
    assert ws.manifest["body_model"]["name"] == "anny" and ws.manifest["downscale"] == 4
    assert ws.manifest["camera"]["width"] == 64
    assert sorted(p.name for p in workspace.iterdir()) == ["avatar", "body_template.npz", "workspace.json"]


def test_existing_workspace_is_refused_without_force(workspace: Path):
    before = (workspace / "avatar" / "000.ply").read_bytes()
    result = invoke("train-initial", SAMPLE / "train", workspace, *TRAIN_ARGS)
    assert result.exit_code == 2 and "--force" in result.stderr
    assert (workspace / "avatar" / "000.ply").read_bytes() == before


def test_interrupted_training_leaves_nothing(tmp_path: Path, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(train_initial_stage, "train", interrupted)
    result = invoke("train-initial", SAMPLE / "train", tmp_path / "ws", *TRAIN_ARGS)
    assert result.exit_code == 130
    assert list(tmp_path.iterdir()) == []


def test_the_gaussian_cap_reaches_the_densification(tmp_path: Path, monkeypatch):
    caps = []

    def recorded(*args, config, **kwargs):
        caps.append(config.densify.max_gaussians)
        raise KeyboardInterrupt

    monkeypatch.setattr(train_initial_stage, "train", recorded)
    invoke("train-initial", SAMPLE / "train", tmp_path / "ws", *TRAIN_ARGS, "--max-gaussians", "1234")
    invoke("train-initial", SAMPLE / "train", tmp_path / "ws", *TRAIN_ARGS)
    assert caps == [1234, 60_000]


def test_bad_dataset_is_one_line(tmp_path: Path):
    result = invoke("train-initial", tmp_path / "nowhere", tmp_path / "ws", *TRAIN_ARGS)
    assert result.exit_code == 2 and len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "ws").exists()


def test_evaluate_writes_metrics_and_grid(workspace: Path):
    result = invoke("evaluate", workspace, "--test", SAMPLE / "test", "--frames", "0:19:5")
    assert result.exit_code == 0, result.output
    metrics = json.loads((workspace / "eval" / "000" / "test" / "metrics.json").read_text())
    assert metrics["frames"] == 4 and len(metrics["per_frame"]) == 4
    # 40 steps at 64² already give a recognisable silhouette.
    assert 0.5 < metrics["mean"]["iou"] <= 1 and 10 < metrics["mean"]["psnr"] < 60 and 0 < metrics["mean"]["ssim"] <= 1
    grid = read_image(workspace / "eval" / "000" / "test" / "comparison.png")
    assert grid.shape[1] == 3 * 64


def test_evaluate_runs_beside_a_stage_that_holds_the_lock(workspace: Path):
    """Scoring a committed avatar reads it without the lock, so a refine in progress does not block it."""
    with workspace_lock(workspace):
        result = invoke("evaluate", workspace, "--test", SAMPLE / "test", "--frames", "0:19:10")
        assert result.exit_code == 0, result.output
    assert json.loads((workspace / "eval" / "000" / "test" / "metrics.json").read_text())["frames"] == 2


def test_evaluate_with_refined_poses_reports_both(workspace: Path):
    result = invoke("evaluate", workspace, "--test", SAMPLE / "test", "--frames", "0:19:5", "--refine-poses")
    assert result.exit_code == 0, result.output
    assert "given" in result.stderr and "refined" in result.stderr
    out = workspace / "eval" / "000" / "test"
    metrics = json.loads((out / "metrics.json").read_text())
    refined = metrics["refined_poses"]
    assert len(refined["per_frame"]) == 4 and [f["frame"] for f in refined["per_frame"]] == [f["frame"] for f in metrics["per_frame"]]
    assert 0.5 < refined["mean"]["iou"] <= 1 and 10 < refined["mean"]["psnr"] < 60
    assert read_image(out / "comparison_refined.png").shape == read_image(out / "comparison.png").shape


def test_render_motion_turntable_and_pose(workspace: Path, tmp_path: Path):
    motion = Path(__file__).resolve().parents[2] / "examples" / "motions" / "walk.npz"
    assert invoke("render", workspace, "--motion", motion, "-o", tmp_path / "walk.mp4").exit_code == 0
    assert (tmp_path / "walk.mp4").stat().st_size > 1000
    assert invoke("render", workspace, "--turntable", 3, "-o", tmp_path / "turn").exit_code == 0
    frames = sorted((tmp_path / "turn").iterdir())
    assert [f.name for f in frames] == ["frame_0000.png", "frame_0001.png", "frame_0002.png"]
    assert read_image(frames[1]).shape == (64, 64, 3)

    manifest = open_workspace(workspace).manifest
    pose = {"body_pose": manifest["reference_pose"]["body_pose"], "transl": manifest["reference_pose"]["transl"], "camera": manifest["camera"]}
    (tmp_path / "pose.json").write_text(json.dumps(pose))
    assert invoke("render", workspace, "--pose", tmp_path / "pose.json", "-o", tmp_path / "posed.png").exit_code == 0
    alpha = read_image(tmp_path / "posed_alpha.png", mode="L")
    assert 0.02 < float((alpha > 0.5).float().mean()) < 0.6


def test_render_needs_a_form(workspace: Path, tmp_path: Path):
    result = invoke("render", workspace, "-o", tmp_path / "x.png")
    assert result.exit_code == 2 and "--pose" in result.stderr


def test_same_seed_same_ply(workspace: Path, tmp_path: Path):
    again = tmp_path / "again"
    assert invoke("train-initial", SAMPLE / "train", again, *TRAIN_ARGS).exit_code == 0
    assert (again / "avatar" / "000.ply").read_bytes() == (workspace / "avatar" / "000.ply").read_bytes()


def test_refine_poses_stores_the_fitted_poses(tmp_path: Path):
    """--refine-poses fits the poses to the masks before training and stores them; the sample's poses are
    exact, so the fitted ones stay near them."""
    import numpy as np

    from avatarperfect_cli.datasets import FrameRange, load_people_snapshot

    result = invoke("train-initial", SAMPLE / "train", tmp_path / "ws", *TRAIN_ARGS[:2], "--resolution", "32", "--frames", "0:59:20", "--refine-poses")
    assert result.exit_code == 0, result.output
    assert "poses fitted to the masks" in result.output
    assert (tmp_path / "ws" / train_initial_stage.BODY_FIT_PICTURE).is_file()
    assert open_workspace(tmp_path / "ws").manifest["refined_poses"] == "poses.npz"
    video = load_people_snapshot(SAMPLE / "train", FrameRange(0, 59, 20))
    with np.load(tmp_path / "ws" / "poses.npz") as poses:
        np.testing.assert_array_equal(poses["frame_ids"], [0, 20, 40])
        assert poses["body_pose"].shape == (3, 24, 3) and poses["transl"].shape == (3, 3)
        assert np.abs(poses["body_pose"] - video.body_pose.numpy()).mean() < np.deg2rad(2.0)


def test_a_fitted_body_is_recorded_for_every_later_stage(tmp_path: Path):
    """--body-shape fit: the picture, and an avatar whose described body rebuilds its own rest joints."""
    import torch

    from avatarperfect_cli.avatar.model import Avatar
    from avatarperfect_cli.body import load_described_template

    result = invoke("train-initial", SAMPLE / "train", tmp_path / "ws", "--iterations", "5", "--resolution", "64",
                    "--frames", "0:59:6", "--body-shape", "fit")  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "body fitted to the masks" in result.output
    ws = open_workspace(tmp_path / "ws")
    assert (tmp_path / "ws" / train_initial_stage.BODY_FIT_PICTURE).is_file()
    avatar = Avatar.load(ws.avatar_path(0))
    body = avatar.body_model
    assert set(body["phenotype"]) == {"gender", "age", "muscle", "weight", "height", "proportions"}
    assert torch.tensor(body["bone_offsets"]).shape == (24, 3)
    torch.testing.assert_close(load_described_template(body).rest_joints, avatar.rest_joints)
    assert ws.manifest["transl_offset"] != [0.0, 0.0, 0.0]


def test_large_frames_trained_at_full_size_get_a_hint(tmp_path: Path, monkeypatch):
    """A user who leaves out --resolution on frames at least twice the usual training size hears what it
    would save; one who gives it does not."""
    monkeypatch.setattr(train_initial_stage, "TYPICAL_RESOLUTION", 64)  # the sample's 256² frames: four times that
    quick = ["--iterations", "1", "--frames", "0:59:30", "--body-shape", "exact"]
    full = invoke("train-initial", SAMPLE / "train", tmp_path / "full", *quick)
    assert full.exit_code == 0, full.output
    assert "(--resolution 64 would train at 64x64, on 16 times fewer pixels)" in full.stderr
    given = invoke("train-initial", SAMPLE / "train", tmp_path / "given", *quick, "--resolution", "128")
    assert given.exit_code == 0 and "--resolution" not in given.stderr
