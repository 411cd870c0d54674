"""make_sample end to end at a tiny size: layout, determinism, framing and the hidden-region bar."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from avatarperfect_cli.datasets.people_snapshot import load_people_snapshot
from avatarperfect_cli.sample import motions
from avatarperfect_cli.sample.generate import make_sample
from avatarperfect_cli.sample.texture import PRESETS


@pytest.fixture(scope="module")
def sample(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sample")
    make_sample(out, resolution=64, seed=2, train_frames=8, test_frames=8)
    return out


def _files(root: Path) -> dict[str, bytes]:
    return {str(path.relative_to(root)): path.read_bytes() for path in sorted(root.rglob("*")) if path.is_file()}


def test_sample_loads_back_in_the_people_snapshot_layout(sample: Path) -> None:
    train = load_people_snapshot(sample / "train")
    test = load_people_snapshot(sample / "test")
    assert train.images.shape == (8, 64, 64, 3) and test.images.shape == (8, 64, 64, 3)
    assert train.camera.width == 64 and train.subject is not None
    assert train.subject["body_model"] == "anny" and train.subject["preset"] == "default"
    assert train.subject["phenotype"] == PRESETS["default"].phenotype
    # The stored poses are the motions (translations are grounded, so only poses compare exactly).
    np.testing.assert_allclose(train.body_pose.numpy(), motions.turntable(8, seed=2).body_pose, atol=1e-6)
    np.testing.assert_allclose(test.body_pose.numpy(), motions.held_out_motion(8).body_pose, atol=1e-6)
    np.testing.assert_allclose(train.camera.K.numpy(), test.camera.K.numpy())
    # The person is in every frame, inside the image, on white.
    for video in (train, test):
        masks = video.masks.numpy()
        assert (masks.mean(axis=(1, 2)) > 0.03).all()
        assert not masks[:, [0, -1], :].any() and not masks[:, :, [0, -1]].any()
        np.testing.assert_array_equal(video.images.numpy()[~masks], 1.0)
        assert video.images.numpy()[masks].mean() < 0.8


def test_same_seed_gives_identical_files(sample: Path, tmp_path: Path) -> None:
    make_sample(tmp_path / "again", resolution=64, seed=2, train_frames=8, test_frames=8)
    assert _files(tmp_path / "again") == _files(sample)


def test_hidden_regions_are_rare_in_training_and_common_in_testing(sample: Path) -> None:
    train = json.loads((sample / "train" / "subject.json").read_text())["hidden_region_fraction"]
    test = json.loads((sample / "test" / "subject.json").read_text())["hidden_region_fraction"]
    # Both shares count the same hidden pixels: one over the masks' pixels, one over all pixels.
    masks = load_people_snapshot(sample / "train").masks.numpy()
    assert train["of_foreground"] * masks.sum() == pytest.approx(train["of_image"] * masks.size)
    assert train["of_foreground"] == pytest.approx(train["inner_arm"] + train["armpit"] + train["crotch"])
    assert train["of_foreground"] < 0.05
    assert test["of_foreground"] > 1.5 * train["of_foreground"]


def test_committed_sample_loads_and_matches_its_description() -> None:
    root = Path(__file__).resolve().parents[2] / "examples" / "sample"
    train = load_people_snapshot(root / "train")
    test = load_people_snapshot(root / "test")
    assert len(train) == 60 and len(test) == 20 and train.camera.width == 256
    np.testing.assert_allclose(train.body_pose.numpy(), motions.turntable(60, seed=0).body_pose, atol=1e-6)
    np.testing.assert_allclose(test.body_pose.numpy(), motions.held_out_motion(20).body_pose, atol=1e-6)
    assert train.subject["hidden_region_fraction"]["of_foreground"] < 0.05
    assert train.masks.numpy().mean(axis=(1, 2)).min() > 0.03
