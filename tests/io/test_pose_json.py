import json
from pathlib import Path
from typing import Any

import pytest
import torch

from avatarperfect_cli.errors import InputFileError
from avatarperfect_cli.io.pose_json import PoseFile, read_pose, write_pose
from avatarperfect_cli.render.camera import Camera, look_at


def example_pose() -> PoseFile:
    g = torch.Generator().manual_seed(3)
    view = look_at(torch.tensor([2.0, 0.5, 1.0]), torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.0, 0.0, 1.0]))
    K = torch.tensor([[700.0, 0.0, 256.0], [0.0, 700.0, 256.0], [0.0, 0.0, 1.0]])
    return PoseFile(0.3 * torch.randn(24, 3, generator=g), torch.randn(3, generator=g), Camera(K, view, 512, 512))


def test_round_trip_is_exact(tmp_path: Path) -> None:
    pose = example_pose()
    write_pose(tmp_path / "ws" / "pose.json", pose)
    loaded = read_pose(tmp_path / "ws" / "pose.json")
    assert loaded.body_pose.dtype == torch.float32 and loaded.transl.dtype == torch.float32
    assert torch.equal(loaded.body_pose, pose.body_pose)
    assert torch.equal(loaded.transl, pose.transl)
    assert torch.equal(loaded.camera.K, pose.camera.K)
    assert torch.equal(loaded.camera.world_to_camera, pose.camera.world_to_camera)
    assert (loaded.camera.width, loaded.camera.height) == (512, 512)
    data = json.loads((tmp_path / "ws" / "pose.json").read_text())
    assert data["format"] == "avatarperfect.pose" and data["version"] == 1
    assert len(data["body_pose"]) == 24 and set(data["camera"]) == {"K", "world_to_camera", "width", "height"}


def test_shape_checks() -> None:
    pose = example_pose()
    with pytest.raises(ValueError, match="body_pose"):
        PoseFile(torch.zeros(23, 3), pose.transl, pose.camera)
    with pytest.raises(ValueError, match="transl"):
        PoseFile(pose.body_pose, torch.zeros(1, 3), pose.camera)


def pose_dict(**changes: Any) -> dict[str, Any]:
    """A valid hand-written pose object (no format/version keys) with `changes` applied; None deletes a key."""
    data: dict[str, Any] = {
        "body_pose": [[0.0, 0.0, 0.0]] * 24,
        "transl": [0.0, 0.1, 0.0],
        "camera": {
            "K": [[500, 0, 256], [0, 500, 256], [0, 0, 1]],
            "world_to_camera": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]],
            "width": 512,
            "height": 512,
        },
    }
    for key, value in changes.items():
        if value is None:
            del data[key]
        else:
            data[key] = value
    return data


def test_hand_written_file_without_format_keys_loads(tmp_path: Path) -> None:
    (tmp_path / "p.json").write_text(json.dumps(pose_dict()))
    loaded = read_pose(tmp_path / "p.json")
    assert torch.equal(loaded.transl, torch.tensor([0.0, 0.1, 0.0]))
    assert not loaded.body_pose.any() and loaded.camera.world_to_camera[2, 3] == 3.0


def _camera_with(**changes: Any) -> dict[str, Any]:
    camera = pose_dict()["camera"]
    camera.update(changes)
    return camera


MALFORMED: dict[str, tuple[str | dict[str, Any], str]] = {
    "syntax": ('{"body_pose": [[0, 0, 0]],,}', "invalid JSON at line 1, column 27"),
    "camera file": (pose_dict(format="avatarperfect.camera"), "'format' is 'avatarperfect.camera'"),
    "newer version": (pose_dict(version=2), "format version 2 is newer"),
    "missing body_pose": (pose_dict(body_pose=None), "missing key 'body_pose'"),
    "missing camera": (pose_dict(camera=None), "missing key 'camera'"),
    "23 joints": (pose_dict(body_pose=[[0.0, 0.0, 0.0]] * 23), "body_pose has 23 entries, not 24"),
    "joint width": (pose_dict(body_pose=[[0.0, 0.0]] * 24), "body_pose[0] has 2 entries, not 3"),
    "transl nan": (pose_dict(transl=[0.0, float("nan"), 0.0]), "transl[1] is not finite"),
    "transl null": (pose_dict(transl=[0.0, None, 0.0]), "transl[1] is null"),
    "camera not object": (pose_dict(camera=[1, 2]), "'camera' must be a JSON object"),
    "camera missing K": (pose_dict(camera={"width": 1, "height": 1}), "missing key 'camera.K'"),
    "camera width": (pose_dict(camera=_camera_with(width=-4)), "'camera.width' must be a positive integer, got -4"),
    "camera rotation": (
        pose_dict(camera=_camera_with(world_to_camera=[[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]])),
        "'camera.world_to_camera' 3x3 part is not a rotation",
    ),
}


@pytest.mark.parametrize("case", MALFORMED)
def test_malformed_pose_gives_one_line_input_file_error(tmp_path: Path, case: str) -> None:
    content, problem = MALFORMED[case]
    path = tmp_path / "bad_pose.json"
    path.write_text(content if isinstance(content, str) else json.dumps(content))
    with pytest.raises(InputFileError) as caught:
        read_pose(path)
    message = str(caught.value)
    assert "bad_pose.json" in message and problem in message and "\n" not in message


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(InputFileError, match="nope.json: file not found"):
        read_pose(tmp_path / "nope.json")
