"""Procedural motions: formats, rotation composition, and what each motion does to an SMPL-like skeleton."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from avatarperfect_cli.body.skeleton import forward_kinematics
from avatarperfect_cli.io.motion import read_motion
from avatarperfect_cli.rotations import axis_angle_to_matrix
from avatarperfect_cli.sample import motions

EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "motions"

# Approximate SMPL rest joints (T-pose, metres): enough to check directions, independent of any body model.
REST_JOINTS = torch.tensor(
    [[0, 0, 0], [0.06, -0.09, 0], [-0.06, -0.09, 0], [0, 0.11, -0.02], [0.1, -0.47, 0], [-0.1, -0.47, 0],
     [0, 0.24, 0], [0.09, -0.87, -0.04], [-0.09, -0.87, -0.04], [0, 0.3, 0.02], [0.11, -0.93, 0.08],
     [-0.11, -0.93, 0.08], [0, 0.51, 0], [0.07, 0.42, 0], [-0.07, 0.42, 0], [0, 0.6, 0.05], [0.17, 0.45, 0],
     [-0.17, 0.45, 0], [0.43, 0.45, 0], [-0.43, 0.45, 0], [0.68, 0.45, 0], [-0.68, 0.45, 0], [0.76, 0.45, 0],
     [-0.76, 0.45, 0]], dtype=torch.float64,
)  # fmt: skip
J = motions.JOINT


def _joints(motion: motions.Motion) -> np.ndarray:
    """(N, 24, 3) posed joint positions."""
    transforms = forward_kinematics(
        torch.as_tensor(motion.body_pose), REST_JOINTS, torch.as_tensor(motion.transl)
    )
    return (transforms[..., :3, :3] @ REST_JOINTS[..., None])[..., 0].numpy() + transforms[..., :3, 3].numpy()


def test_compose_is_the_matrix_product() -> None:
    rng = np.random.default_rng(0)
    first, then = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    composed = motions.compose(first, then)
    expected = axis_angle_to_matrix(torch.as_tensor(then)) @ axis_angle_to_matrix(torch.as_tensor(first))
    torch.testing.assert_close(axis_angle_to_matrix(torch.as_tensor(composed)), expected)
    assert (np.linalg.norm(composed, axis=1) <= np.pi + 1e-9).all()


@pytest.mark.parametrize(
    "make", [lambda n: motions.turntable(n), motions.walk, motions.raise_arms, motions.legs_apart, motions.squat,
             motions.held_out_motion],  # fmt: skip
)
def test_motions_have_smpl_shapes(make) -> None:
    motion = make(13)
    assert motion.body_pose.shape == (13, 24, 3) and motion.transl.shape == (13, 3)
    assert np.isfinite(motion.body_pose).all() and np.isfinite(motion.transl).all()


def test_turntable_turns_once_in_an_a_pose() -> None:
    motion = motions.turntable(100, seed=3)
    joints = _joints(motion)
    # The body's front (+Z at rest) turns by 360 t / 100 degrees about +Y.
    front = axis_angle_to_matrix(torch.as_tensor(motion.body_pose[:, 0]))[:, :, 2].numpy()
    yaw = np.unwrap(np.arctan2(front[:, 0], front[:, 2]))
    np.testing.assert_allclose(yaw - yaw[0], 2 * np.pi * np.arange(100) / 100, atol=1e-9)
    # A-pose: each wrist hangs 45-65 degrees below its shoulder, away from the body.
    for shoulder, wrist in ((J["left_shoulder"], J["left_wrist"]), (J["right_shoulder"], J["right_wrist"])):
        arm = joints[:, wrist] - joints[:, shoulder]
        drop = np.degrees(np.arcsin(-arm[:, 1] / np.linalg.norm(arm, axis=1)))
        assert ((drop > 45) & (drop < 65)).all()
    # The sway is slight: the legs stay straight and the head stays within 8 degrees.
    assert np.abs(motion.body_pose[:, [J["left_knee"], J["right_knee"]]]).max() == 0
    assert np.linalg.norm(motion.body_pose[:, J["head"]], axis=1).max() < np.radians(8)


def test_turntable_sway_depends_on_the_seed_only() -> None:
    np.testing.assert_array_equal(motions.turntable(20, seed=1).body_pose, motions.turntable(20, seed=1).body_pose)
    assert not np.allclose(motions.turntable(20, seed=1).body_pose, motions.turntable(20, seed=2).body_pose)


def test_held_out_motions_do_what_their_names_say() -> None:
    rest = _joints(motions.Motion(np.zeros((1, 24, 3)), np.zeros((1, 3))))[0]

    walk = _joints(motions.walk(20))
    step = walk[:, J["left_ankle"], 2] - walk[:, J["right_ankle"], 2]
    assert step.max() > 0.3 and step.min() < -0.3  # each foot leads in turn

    raise_arms = _joints(motions.raise_arms(21))
    assert raise_arms[:, J["left_wrist"], 1].max() > rest[J["head"], 1] + 0.2  # hands above the head
    assert raise_arms[0, J["left_wrist"], 1] < rest[J["left_shoulder"], 1] - 0.3  # from hanging arms

    apart = _joints(motions.legs_apart(10))
    width = apart[:, J["left_ankle"], 0] - apart[:, J["right_ankle"], 0]
    assert width[-1] > (rest[J["left_ankle"], 0] - rest[J["right_ankle"], 0]) + 0.5

    squat = _joints(motions.squat(15))
    # In the squat the pelvis comes closer to the ankles and the feet stay roughly flat.
    height = squat[:, J["pelvis"], 1] - squat[:, J["left_ankle"], 1]
    assert height.min() < 0.6 * (rest[J["pelvis"], 1] - rest[J["left_ankle"], 1])
    toe = squat[:, J["left_foot"]] - squat[:, J["left_ankle"]]
    assert np.abs(np.degrees(np.arctan2(-toe[:, 1], toe[:, 2]))).max() < 35


def test_held_out_motion_is_seen_from_several_sides() -> None:
    motion = motions.held_out_motion(30)
    front = axis_angle_to_matrix(torch.as_tensor(motion.body_pose[:, 0]))[:, :, 2].numpy()
    yaw = np.degrees(np.arctan2(front[:, 0], front[:, 2]))
    assert np.histogram(yaw, bins=4, range=(-180, 180))[0].min() >= 2  # front, both sides and back


@pytest.mark.parametrize("name", ["walk", "raise_arms", "squat"])
def test_committed_example_motions(name: str) -> None:
    body_pose, transl = read_motion(EXAMPLES / f"{name}.npz")
    assert body_pose.shape[0] >= 30 and transl.shape == (body_pose.shape[0], 3)
    # The file holds the named motion (float32), grounded: only the vertical translation differs.
    expected = getattr(motions, name)(body_pose.shape[0])
    np.testing.assert_allclose(body_pose.numpy(), expected.body_pose, atol=1e-6)
    np.testing.assert_allclose(transl.numpy()[:, [0, 2]], expected.transl[:, [0, 2]], atol=1e-6)
