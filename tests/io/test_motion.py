"""Motion .npz files (poses (N, 72), trans (N, 3)): round trip and malformed files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from avatarperfect_cli.body import axis_angle_to_matrix, forward_kinematics
from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.io.motion import detect_up_axis, place_motion, read_motion, write_motion


def test_round_trip(tmp_path: Path):
    body_pose = torch.randn(5, 24, 3)
    transl = torch.randn(5, 3)
    write_motion(tmp_path / "m.npz", body_pose, transl)
    read_pose, read_transl = read_motion(tmp_path / "m.npz")
    assert torch.equal(read_pose, body_pose) and torch.equal(read_transl, transl)
    with np.load(tmp_path / "m.npz") as data:
        assert data["poses"].shape == (5, 72) and np.array_equal(data["poses"][:, 3:6], body_pose[:, 1].numpy())


@pytest.mark.parametrize(
    "columns,hint",
    [(69, "without the global orientation"), (156, "SMPL-H layout"), (165, "SMPL-X layout"), (75, None)],
)
def test_other_pose_widths_are_refused_in_one_line_naming_the_layout(tmp_path: Path, columns: int, hint: str | None):
    """SMPL-H's columns 66..71 are finger joints, not SMPL's hands: taking the first 72 would pose the wrong joints."""
    np.savez(tmp_path / "m.npz", poses=np.zeros((3, columns), np.float32), trans=np.zeros((3, 3), np.float32))
    with pytest.raises(InputFileError, match=rf"poses must be \(N, 72\).*got \(3, {columns}\)") as error:
        read_motion(tmp_path / "m.npz")
    message = str(error.value)
    assert "m.npz" in message and "\n" not in message
    assert (hint in message) if hint else ("layout" not in message)


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


# ------------------------------------------------------------------------ which way is up, and placing a motion

FLIP_Y_DOWN = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))  # y-up world -> OpenCV camera axes
Z_UP = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]], dtype=torch.float64)  # y-up -> z-up (AMASS)


def turning_motion(frames: int = 5) -> tuple[torch.Tensor, torch.Tensor]:
    """A y-up motion that starts facing +Z turned by 0.3 rad, then wobbles and walks; random joint angles."""
    generator = torch.Generator().manual_seed(1)
    body_pose = torch.randn(frames, 24, 3, generator=generator, dtype=torch.float64) * 0.3
    steps = torch.arange(frames, dtype=torch.float64)
    body_pose[:, 0] = torch.stack([0.1 * torch.sin(steps), 0.3 + 0.2 * steps, 0.05 * steps], dim=1)
    transl = torch.stack([0.1 * steps, 0.02 * torch.cos(steps), -0.05 * steps], dim=1)
    transl += torch.tensor([0.3, 0.9, -0.2], dtype=torch.float64)
    return body_pose, transl


def convert_world(body_pose: torch.Tensor, transl: torch.Tensor, rotation: torch.Tensor, rest_pelvis: torch.Tensor):
    """The same motion stored in a world turned by `rotation` (3, 3): the roots' orientations and positions
    (rest pelvis + transl) turn with it, as a tool writing in that frame would store them."""
    from avatarperfect_cli.rotations import matrix_to_axis_angle

    converted = body_pose.clone()
    converted[:, 0] = matrix_to_axis_angle(rotation @ axis_angle_to_matrix(body_pose[:, 0]))
    return converted, (rest_pelvis + transl) @ rotation.T - rest_pelvis


def joint_positions(body_pose: torch.Tensor, transl: torch.Tensor, rest_joints: torch.Tensor) -> torch.Tensor:
    """(N, 24, 3) float64 posed joints, an independent view of where a placed motion puts the body."""
    transforms = forward_kinematics(body_pose.double(), rest_joints.double(), transl.double())
    return transforms[:, :, :3, :3] @ rest_joints.double()[None, :, :, None] + transforms[:, :, :3, 3:]


@pytest.mark.parametrize("rotation,up", [(torch.eye(3, dtype=torch.float64), "y"), (FLIP_Y_DOWN, "-y"), (Z_UP, "z")])
def test_the_up_axis_is_detected_from_the_first_frame(rotation: torch.Tensor, up: str):
    body_pose, transl = turning_motion()
    converted, _ = convert_world(body_pose, transl, rotation, torch.zeros(3, dtype=torch.float64))
    assert detect_up_axis(converted.float(), Path("m.npz")) == up


def test_a_sideways_body_cannot_be_told_and_says_so():
    body_pose = torch.zeros(2, 24, 3)
    body_pose[:, 0, 2] = math.pi / 2  # SMPL's +Y turned onto -X
    with pytest.raises(AvatarPerfectError, match=r"m.npz: cannot tell which way is up.*-x.*--up"):
        detect_up_axis(body_pose, Path("m.npz"))


@pytest.mark.parametrize("rotation,up", [(FLIP_Y_DOWN, "-y"), (Z_UP, "z")])
def test_a_motion_in_another_world_is_placed_like_the_y_up_original(rotation: torch.Tensor, up: str):
    """The same motion stored y-down (camera frame) or z-up gives the same joints in the render world."""
    rest_joints = torch.randn(24, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64) * 0.3
    body_pose, transl = turning_motion()
    converted, converted_transl = convert_world(body_pose, transl, rotation, rest_joints[0])
    place = {
        "world_up": torch.tensor([0.0, 1.0, 0.0]),
        "toward_camera": torch.tensor([0.2, 0.1, 3.0]),
        "start": torch.tensor([0.5, -0.1, 0.2]),
    }
    original = joint_positions(*place_motion(body_pose.float(), transl.float(), "y", **place), rest_joints)
    placed = joint_positions(*place_motion(converted.float(), converted_transl.float(), up, **place), rest_joints)
    torch.testing.assert_close(placed, original, atol=1e-5, rtol=0)
    misread = joint_positions(*place_motion(converted.float(), converted_transl.float(), "y", **place), rest_joints)
    assert (misread - original).abs().max() > 0.3  # read as y-up, the body is upside down


def test_placing_faces_the_camera_and_keeps_the_root_path():
    """Checked against the definition: the first frame's front points at the camera seen from above, its root
    sits at start, and the root path is the motion's, turned about the up axis by the same angle."""
    rest_joints = torch.zeros(24, 3, dtype=torch.float64)
    body_pose, transl = turning_motion()
    world_up, toward, start = torch.tensor([0.0, 0.0, 1.0]), torch.tensor([1.0, 1.0, 0.4]), torch.tensor([1.0, 2.0, 3.0])
    placed_pose, placed_transl = place_motion(body_pose.float(), transl.float(), "y", world_up, toward, start)
    front = axis_angle_to_matrix(placed_pose[0, 0].double())[:, 2]
    diagonal = torch.tensor([1.0, 1.0], dtype=torch.float64) / math.sqrt(2)
    torch.testing.assert_close(front[:2] / front[:2].norm(), diagonal, atol=1e-5, rtol=0)
    body_up = axis_angle_to_matrix(placed_pose[0, 0].double())[:, 1]
    original_up = axis_angle_to_matrix(body_pose[0, 0])[:, 1]
    assert abs(float(body_up[2]) - float(original_up[1])) < 1e-5  # the tilt from vertical is kept
    torch.testing.assert_close(placed_transl[0], start)
    steps = (placed_transl - placed_transl[:1]).double()
    original_steps = transl - transl[:1]
    torch.testing.assert_close(steps.norm(dim=1), original_steps.norm(dim=1), atol=1e-5, rtol=0)
    torch.testing.assert_close(steps[:, 2], original_steps[:, 1], atol=1e-5, rtol=0)  # heights stay heights
    torch.testing.assert_close(placed_pose[:, 1:], body_pose[:, 1:].float())  # only the root turns
