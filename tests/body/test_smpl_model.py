"""SMPL templates through smplx, from a small fake model file with the real file's keys."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from avatarperfect_cli.body import load_body_template
from avatarperfect_cli.body.base import NUM_JOINTS, SMPL_PARENTS
from avatarperfect_cli.body.smpl_model import load_smpl_template
from avatarperfect_cli.errors import AvatarPerfectError, InputFileError

pytest.importorskip("smplx")

VERTICES = 60


def _fake_model(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    weights = rng.random((VERTICES, NUM_JOINTS)) ** 4
    regressor = rng.random((NUM_JOINTS, VERTICES))
    kintree = np.stack([np.array(SMPL_PARENTS) % 2**32, np.arange(NUM_JOINTS)]).astype(np.int64)
    return {
        "v_template": rng.normal(size=(VERTICES, 3)),
        "shapedirs": 0.1 * rng.normal(size=(VERTICES, 3, 10)),
        "posedirs": 0.01 * rng.normal(size=(VERTICES, 3, 207)),
        "J_regressor": regressor / regressor.sum(1, keepdims=True),
        "weights": weights / weights.sum(1, keepdims=True),
        "kintree_table": kintree,
        "f": rng.integers(0, VERTICES, size=(40, 3)).astype(np.uint32),
    }


def _write_pkl(folder: Path, name: str, data: dict[str, np.ndarray]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    with (folder / name).open("wb") as file:
        pickle.dump(data, file)


@pytest.mark.parametrize("betas", [None, [0.5, -1.0, 2.0]])
def test_template_from_fake_pkl_matches_the_smpl_formulas(tmp_path: Path, betas: list[float] | None) -> None:
    data = _fake_model()
    _write_pkl(tmp_path, "SMPL_NEUTRAL.pkl", data)
    template = load_smpl_template(tmp_path, betas=betas)
    shape = np.zeros(10)
    shape[: len(betas or [])] = betas or []
    expected_vertices = data["v_template"] + data["shapedirs"] @ shape
    np.testing.assert_allclose(template.vertices.numpy(), expected_vertices, atol=1e-5)
    np.testing.assert_allclose(template.rest_joints.numpy(), data["J_regressor"] @ expected_vertices, atol=1e-5)
    np.testing.assert_allclose(template.weights.numpy(), data["weights"], atol=1e-6)
    assert template.faces.dtype == torch.int64
    assert np.array_equal(template.faces.numpy(), data["f"].astype(np.int64))
    assert template.vertices.dtype == torch.float32 and template.uvs is None


def test_npz_in_smpl_subfolder_and_gender(tmp_path: Path) -> None:
    data = _fake_model(seed=1)
    (tmp_path / "smpl").mkdir()
    np.savez(tmp_path / "smpl" / "SMPL_FEMALE.npz", **data)
    template = load_body_template("smpl", smpl_model_dir=tmp_path, gender="female")
    np.testing.assert_allclose(template.vertices.numpy(), data["v_template"], atol=1e-5)
    with pytest.raises(InputFileError, match="SMPL_MALE"):
        load_body_template("smpl", smpl_model_dir=tmp_path, gender="male")


def test_bad_inputs_raise_one_line_errors(tmp_path: Path) -> None:
    with pytest.raises(InputFileError, match="not found"):
        load_smpl_template(tmp_path / "missing")
    with pytest.raises(InputFileError, match="SMPL_NEUTRAL.pkl"):
        load_smpl_template(tmp_path)
    with pytest.raises(AvatarPerfectError, match="smpl-model-dir"):
        load_body_template("smpl")
    with pytest.raises(AvatarPerfectError, match="unknown body model"):
        load_body_template("mano")

    broken = _fake_model()
    del broken["J_regressor"]
    _write_pkl(tmp_path / "a", "SMPL_NEUTRAL.pkl", broken)
    with pytest.raises(InputFileError, match="J_regressor"):
        load_smpl_template(tmp_path / "a")

    wrong_tree = _fake_model()
    wrong_tree["kintree_table"][0, 5] = 0
    _write_pkl(tmp_path / "b", "SMPL_NEUTRAL.pkl", wrong_tree)
    with pytest.raises(InputFileError, match="kinematic tree"):
        load_smpl_template(tmp_path / "b")

    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "SMPL_NEUTRAL.pkl").write_bytes(b"not a pickle")
    with pytest.raises(InputFileError) as error:
        load_smpl_template(tmp_path / "c")
    assert "\n" not in str(error.value)
