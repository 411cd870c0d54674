"""Portable workspaces: the dataset is stored relative to the workspace, and `relink` points a workspace at its
moved video after checking that it is the same one; a workspace copied alone reads the video from its absolute
path. On a copy of the committed sample shrunk to 64²."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from avatarperfect_cli.io import read_image, write_image
from tests.stages.test_refinement_stages import FAST_SUGGEST, SAMPLE, TRAIN_ARGS, invoke, one_line_error, snapshot


@pytest.fixture()
def original(tmp_path: Path) -> Path:
    """old/ holding data/train (a copy of the sample's video) and ws/ trained on it."""
    box = tmp_path / "old"
    shutil.copytree(SAMPLE / "train", box / "data" / "train")
    result = invoke("train-initial", box / "data" / "train", box / "ws", *TRAIN_ARGS)
    assert result.exit_code == 0, result.output
    return box


def manifest(workspace: Path) -> dict:
    return json.loads((workspace / "workspace.json").read_text())


def run_the_stages(workspace: Path) -> None:
    """visibility, suggest, refine and evaluate all work on the workspace."""
    for command in (
        ("visibility", workspace), ("suggest", workspace, *FAST_SUGGEST), ("refine", workspace, "--iterations", "3"),
        ("evaluate", workspace, "--test", SAMPLE / "test", "--frames", "0:19:10"),
    ):  # fmt: skip
        result = invoke(*command)
        assert result.exit_code == 0, (command, result.output)


def moved(original: Path, tmp_path: Path, workspace: str, dataset: str) -> tuple[Path, Path]:
    """Copies of the workspace and its video at tmp_path/<workspace> and tmp_path/<dataset>."""
    shutil.copytree(original / "ws", tmp_path / workspace)
    shutil.copytree(original / "data" / "train", tmp_path / dataset)
    return tmp_path / workspace, tmp_path / dataset


def test_train_initial_records_the_dataset_relative_to_the_workspace_and_its_fingerprint(original: Path):
    recorded = manifest(original / "ws")
    assert recorded["dataset"] == "../data/train" and recorded["dataset_absolute"] == str(original / "data" / "train")
    fingerprint = recorded["dataset_fingerprint"]
    assert (fingerprint["frames"], fingerprint["width"], fingerprint["height"]) == (60, 256, 256)
    assert len(fingerprint["sha256"]) == 64


def test_a_workspace_moved_with_its_dataset_needs_no_relink(original: Path, tmp_path: Path):
    moved_box = tmp_path / "elsewhere" / "box"
    shutil.copytree(original, moved_box)
    shutil.rmtree(original)
    run_the_stages(moved_box / "ws")


def test_a_dataset_moved_elsewhere_works_after_one_relink(original: Path, tmp_path: Path):
    workspace, dataset = moved(original, tmp_path, "project/ws", "videos/subject")
    shutil.rmtree(original)
    before = snapshot(workspace)
    assert "avatarperfect relink" in one_line_error(invoke("visibility", workspace))
    assert snapshot(workspace) == before
    result = invoke("relink", workspace, dataset)
    assert result.exit_code == 0, result.output
    assert manifest(workspace)["dataset"] == "../../videos/subject"
    assert manifest(workspace)["dataset_absolute"] == str(dataset)
    assert manifest(workspace)["history"][-1]["stage"] == "relink"
    run_the_stages(workspace)


@pytest.mark.parametrize("change", ["fewer frames", "another image", "another size"])
def test_relink_refuses_another_video_and_changes_nothing(original: Path, tmp_path: Path, change: str):
    workspace, dataset = moved(original, tmp_path, "ws", "video")
    if change == "fewer frames":
        (dataset / "images" / "image_0059.png").unlink()
        finding = "59 frames, but the workspace's video has 60"
    elif change == "another image":
        image = read_image(dataset / "images" / "image_0007.png", "RGB")
        write_image(dataset / "images" / "image_0007.png", 1.0 - image)
        finding = "content hash"
    else:
        with np.load(dataset / "cameras.npz") as data:
            cameras = dict(data)
        np.savez(dataset / "cameras.npz", **cameras | {"width": np.array(128), "height": np.array(128)})
        finding = "128x128 images, but the workspace's video has 256x256"
    before = snapshot(workspace)
    assert finding in one_line_error(invoke("relink", workspace, dataset))
    assert snapshot(workspace) == before


def test_a_workspace_without_a_fingerprint_is_checked_by_size_and_frames_and_gets_one(original: Path, tmp_path: Path):
    workspace, dataset = moved(original, tmp_path, "ws", "video")
    older = manifest(workspace)
    del older["dataset_fingerprint"], older["dataset_absolute"]
    older["dataset"] = str(tmp_path / "gone")
    (workspace / "workspace.json").write_text(json.dumps(older))
    result = invoke("relink", workspace, dataset)
    assert result.exit_code == 0, result.output
    assert "had no fingerprint" in result.stderr
    assert manifest(workspace)["dataset_fingerprint"] == manifest(original / "ws")["dataset_fingerprint"]
    run_the_stages(workspace)


def test_a_workspace_copied_without_its_dataset_reads_it_from_the_absolute_path(original: Path, tmp_path: Path):
    workspace = tmp_path / "deeper" / "still" / "ws"
    shutil.copytree(original / "ws", workspace)
    assert not (workspace / manifest(workspace)["dataset"]).is_dir()
    run_the_stages(workspace)
