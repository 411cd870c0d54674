"""Motion .npz files (poses (N, 72), trans (N, 3)): round trip and malformed files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from avatarperfect_cli.errors import InputFileError
from avatarperfect_cli.io.motion import read_motion, write_motion


def test_round_trip(tmp_path: Path):
    body_pose = torch.randn(5, 24, 3)
    transl = torch.randn(5, 3)
    write_motion(tmp_path / "m.npz", body_pose, transl)
    read_pose, read_transl = read_motion(tmp_path / "m.npz")
    assert torch.equal(read_pose, body_pose) and torch.equal(read_transl, transl)
    with np.load(tmp_path / "m.npz") as data:
        assert data["poses"].shape == (5, 72) and np.array_equal(data["poses"][:, 3:6], body_pose[:, 1].numpy())


def test_smplh_width_poses_keep_the_body_joints(tmp_path: Path):
    poses = np.random.default_rng(0).normal(size=(3, 156)).astype(np.float32)
    np.savez(tmp_path / "m.npz", poses=poses, trans=np.zeros((3, 3), np.float32))
    body_pose, _ = read_motion(tmp_path / "m.npz")
    assert np.array_equal(body_pose.reshape(3, 72).numpy(), poses[:, :72])


@pytest.mark.parametrize(
    "arrays,problem",
    [
        ({"poses": np.zeros((3, 72))}, "missing 'trans'"),
        ({"poses": np.zeros((3, 60)), "trans": np.zeros((3, 3))}, "poses must be"),
        ({"poses": np.zeros((3, 72)), "trans": np.zeros((2, 3))}, "trans must be"),
        ({"poses": np.full((3, 72), np.nan), "trans": np.zeros((3, 3))}, "NaN"),
    ],
)
def test_malformed(tmp_path: Path, arrays, problem):
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(InputFileError, match=problem) as error:
        read_motion(tmp_path / "bad.npz")
    assert "bad.npz" in str(error.value)


@pytest.mark.parametrize(
    "arrays,problem",
    [
        ({"poses": np.full((3, 72), "0.1"), "trans": np.zeros((3, 3))}, "'poses' holds <U3 values, not numbers"),
        ({"poses": np.zeros((3, 72)), "trans": np.zeros((3, 3), np.complex64)}, "'trans' holds complex64 values"),
        ({"poses": np.array([None, None], dtype=object), "trans": np.zeros((2, 3))}, "not a readable .npz motion"),
    ],
)
def test_values_that_are_not_numbers(tmp_path: Path, arrays, problem):
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(InputFileError, match=problem):
        read_motion(tmp_path / "bad.npz")


def test_a_single_npy_array_is_refused(tmp_path: Path):
    path = tmp_path / "walk.npy"
    np.save(path, np.zeros((3, 72), np.float32))
    with pytest.raises(InputFileError, match="single .npy array") as error:
        read_motion(path)
    assert "walk.npy" in str(error.value)


def test_not_an_npz(tmp_path: Path):
    (tmp_path / "m.npz").write_text("hello")
    with pytest.raises(InputFileError, match="not a readable"):
        read_motion(tmp_path / "m.npz")
