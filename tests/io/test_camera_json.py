import json
import math
from pathlib import Path
from typing import Any

import pytest
import torch

from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.io.camera_json import MAX_IMAGE_SIDE_VARIABLE, read_camera, write_camera
from avatarperfect_cli.render.camera import Camera, look_at


def example_camera() -> Camera:
    view = look_at(torch.tensor([0.3, -2.5, 1.1]), torch.tensor([0.0, 0.0, 0.9]), torch.tensor([0.0, 0.0, 1.0]))
    K = torch.tensor([[612.3, 0.0, 270.1], [0.0, 611.7, 269.4], [0.0, 0.0, 1.0]])
    return Camera(K, view, 540, 540)


def camera_dict() -> dict[str, Any]:
    """A valid camera JSON object written by hand (no format/version keys)."""
    c, s = math.cos(0.4), math.sin(0.4)
    return {
        "K": [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0, 0, 1]],
        "world_to_camera": [[c, -s, 0.0, 0.1], [s, c, 0.0, -0.2], [0.0, 0.0, 1.0, 3.0], [0, 0, 0, 1]],
        "width": 640,
        "height": 480,
    }


def test_round_trip_is_exact(tmp_path: Path) -> None:
    camera = example_camera()
    write_camera(tmp_path / "cam.json", camera)
    loaded = read_camera(tmp_path / "cam.json")
    assert loaded.K.dtype == torch.float32 and loaded.world_to_camera.dtype == torch.float32
    assert torch.equal(loaded.K, camera.K)
    assert torch.equal(loaded.world_to_camera, camera.world_to_camera)
    assert (loaded.width, loaded.height) == (540, 540)
    data = json.loads((tmp_path / "cam.json").read_text())
    assert data["format"] == "avatarperfect.camera" and data["version"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cam.json"]


def test_file_without_format_keys_loads(tmp_path: Path) -> None:
    data = camera_dict()
    (tmp_path / "cam.json").write_text(json.dumps(data))
    loaded = read_camera(tmp_path / "cam.json")
    assert torch.equal(loaded.K, torch.tensor(data["K"], dtype=torch.float32))
    assert torch.equal(loaded.world_to_camera, torch.tensor(data["world_to_camera"], dtype=torch.float32))
    assert (loaded.width, loaded.height) == (640, 480)


def modified(**changes: Any) -> dict[str, Any]:
    data = camera_dict()
    for key, value in changes.items():
        if value is None:
            del data[key]
        else:
            data[key] = value
    return data


def _scaled_rotation() -> list[list[float]]:
    matrix = camera_dict()["world_to_camera"]
    matrix[0][:3] = [1.01 * v for v in matrix[0][:3]]
    return matrix


def _reflection() -> list[list[float]]:
    matrix = camera_dict()["world_to_camera"]
    matrix[2][2] = -1.0
    return matrix


MALFORMED: dict[str, tuple[str | dict[str, Any], str]] = {
    "syntax": ('{\n  "K": [[1, 0, 0],\n  oops\n}', "invalid JSON at line 3, column 3"),
    "top-level array": ("[1, 2]", "expected a JSON object at the top level, got an array"),
    "wrong format": (modified(format="avatarperfect.pose"), "'format' is 'avatarperfect.pose'"),
    "newer version": (modified(version=7), "format version 7 is newer"),
    "missing K": (modified(K=None), "missing key 'K'"),
    "missing height": (modified(height=None), "missing key 'height'"),
    "K rows": (modified(K=[[1.0, 0.0, 0.0], [0.0, 1.0], [0.0, 0.0, 1.0]]), "'K' must be a 3x3 array"),
    "K flat": (modified(K=[1.0] * 9), "K has 9 entries, not 3"),
    "K vector": (modified(K=[1.0, 0.0, 1.0]), "K[0] is a number, not an array of 3"),
    "string entry": (modified(width=3, K=[[1, 0, "0"], [0, 1, 0], [0, 0, 1]]), "K[0][2] is a string"),
    "view shape": (modified(world_to_camera=[[1, 0, 0, 0]] * 3), "world_to_camera has 3 entries, not 4"),
    "nan": (modified(K=[[float("nan"), 0, 0], [0, 1, 0], [0, 0, 1]]), "K[0][0] is not finite"),
    "infinity": ('{"K": [[1e999, 0, 0], [0, 1, 0], [0, 0, 1]]}', "K[0][0] is not finite"),
    "zero width": (modified(width=0), "'width' must be a positive integer, got 0"),
    "fractional height": (modified(height=480.5), "'height' must be a positive integer, got 480.5"),
    "boolean width": (modified(width=True), "'width' must be a positive integer, got True"),
    "negative focal": (modified(K=[[-500, 0, 320], [0, 500, 240], [0, 0, 1]]), "positive focal lengths"),
    "zero focal": (modified(K=[[500, 0, 320], [0, 0, 240], [0, 0, 1]]), "positive focal lengths"),
    "K last row": (modified(K=[[500, 0, 320], [0, 500, 240], [0, 0.5, 1]]), "last row [0, 0, 1]"),
    "beyond float32": (modified(K=[[1e39, 0, 320], [0, 500, 240], [0, 0, 1]]), "'K' holds values too large for float32"),
    "huge image": (modified(width=30000, height=30000), "image size 30000x30000 exceeds the maximum side of 8192 px"),
    "not a rotation": (modified(world_to_camera=_scaled_rotation()), "3x3 part is not a rotation"),
    "reflection": (modified(world_to_camera=_reflection()), "reflection"),
    "view last row": (
        modified(world_to_camera=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]),
        "last row [0, 0, 0, 1]",
    ),
}


@pytest.mark.parametrize("case", MALFORMED)
def test_malformed_camera_gives_one_line_input_file_error(tmp_path: Path, case: str) -> None:
    content, problem = MALFORMED[case]
    path = tmp_path / "bad_cam.json"
    path.write_text(content if isinstance(content, str) else json.dumps(content))
    with pytest.raises(InputFileError) as caught:
        read_camera(path)
    message = str(caught.value)
    assert "bad_cam.json" in message and problem in message and "\n" not in message


def test_unreadable_files(tmp_path: Path) -> None:
    with pytest.raises(InputFileError, match="file not found"):
        read_camera(tmp_path / "nope.json")
    (tmp_path / "latin1.json").write_bytes(b'{"K": "\xe9"}')
    with pytest.raises(InputFileError, match="not a UTF-8 text file"):
        read_camera(tmp_path / "latin1.json")


def test_the_maximum_image_side_follows_the_environment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "big.json"
    path.write_text(json.dumps(modified(width=9000, height=100)))
    with pytest.raises(InputFileError, match="maximum side of 8192 px"):
        read_camera(path)
    monkeypatch.setenv(MAX_IMAGE_SIDE_VARIABLE, "9000")
    assert read_camera(path).width == 9000
    monkeypatch.setenv(MAX_IMAGE_SIDE_VARIABLE, "8999")
    with pytest.raises(InputFileError, match="maximum side of 8999 px"):
        read_camera(path)
    monkeypatch.setenv(MAX_IMAGE_SIDE_VARIABLE, "lots")
    with pytest.raises(AvatarPerfectError, match=MAX_IMAGE_SIDE_VARIABLE):
        read_camera(path)
