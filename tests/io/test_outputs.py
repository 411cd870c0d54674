"""Output checks made before the work, and image pairs that appear together or not at all."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from avatarperfect_cli.errors import InputFileError
from avatarperfect_cli.io import outputs
from avatarperfect_cli.io.outputs import check_writable_folder, check_writable_output, write_image_pair


def test_a_file_in_a_missing_folder_is_writable_and_nothing_is_created(tmp_path: Path):
    check_writable_output(tmp_path / "a" / "b" / "x.png")
    check_writable_folder(tmp_path / "c" / "frames")
    assert list(tmp_path.iterdir()) == []


def test_an_existing_folder_is_not_a_file_name(tmp_path: Path):
    (tmp_path / "x.png").mkdir()
    with pytest.raises(InputFileError, match="is a folder; give a file name") as caught:
        check_writable_output(tmp_path / "x.png")
    assert caught.value.path == tmp_path / "x.png"


def test_a_file_is_not_a_folder(tmp_path: Path):
    (tmp_path / "frames").write_text("")
    with pytest.raises(InputFileError, match="exists and is not a folder"):
        check_writable_folder(tmp_path / "frames")


def test_a_parent_that_is_a_file_cannot_hold_outputs(tmp_path: Path):
    (tmp_path / "notes.txt").write_text("")
    with pytest.raises(InputFileError, match=f"{tmp_path / 'notes.txt'} is not a folder") as caught:
        check_writable_output(tmp_path / "notes.txt" / "sub" / "x.png")
    assert caught.value.path == tmp_path / "notes.txt" / "sub" / "x.png"


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_folder_is_refused(tmp_path: Path):
    folder = tmp_path / "locked"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        with pytest.raises(InputFileError, match="is not writable"):
            check_writable_output(folder / "x.png")
        with pytest.raises(InputFileError, match="is not writable"):
            check_writable_folder(folder / "frames")
    finally:
        folder.chmod(0o755)


def test_the_os_verdict_on_the_nearest_existing_folder_decides(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """Runs as root too: os.access is asked about the nearest existing ancestor, and its answer is obeyed."""
    asked = []

    def access(path: object, mode: int) -> bool:
        asked.append(Path(path))
        return False

    monkeypatch.setattr(outputs.os, "access", access)
    with pytest.raises(InputFileError, match=f"folder {tmp_path} is not writable"):
        check_writable_output(tmp_path / "missing" / "x.png")
    assert asked == [tmp_path]


def pixels(seed: int, channels: int) -> torch.Tensor:
    return torch.rand(6, 5, channels, generator=torch.Generator().manual_seed(seed))


def read_back(path: Path) -> np.ndarray:
    with Image.open(path) as image:
        return np.asarray(image)


def test_pair_writes_both_images(tmp_path: Path):
    rgb, alpha = pixels(0, 3), pixels(1, 1)
    write_image_pair(tmp_path / "sub" / "r.png", rgb, tmp_path / "sub" / "r_alpha.png", alpha)
    np.testing.assert_array_equal(read_back(tmp_path / "sub" / "r.png"), (rgb * 255).round().to(torch.uint8).numpy())
    np.testing.assert_array_equal(read_back(tmp_path / "sub" / "r_alpha.png"), (alpha[..., 0] * 255).round().to(torch.uint8).numpy())
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == ["r.png", "r_alpha.png"]


def test_pair_with_an_unwritable_second_path_writes_nothing(tmp_path: Path):
    (tmp_path / "r_alpha.png").mkdir()
    with pytest.raises(InputFileError, match="r_alpha.png: is a folder"):
        write_image_pair(tmp_path / "r.png", pixels(0, 3), tmp_path / "r_alpha.png", pixels(1, 1))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r_alpha.png"]


@pytest.mark.parametrize("first_existed", [False, True])
def test_a_failing_second_rename_rolls_the_first_back(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, first_existed: bool):
    first, second = tmp_path / "r.png", tmp_path / "r_alpha.png"
    if first_existed:
        first.write_bytes(b"the previous render")
    real_replace = os.replace

    def replace(source: object, target: object) -> None:
        if Path(target) == second:
            raise OSError(28, "No space left on device")
        real_replace(source, target)

    monkeypatch.setattr(outputs.os, "replace", replace)
    with pytest.raises(InputFileError, match="r_alpha.png: cannot be written: No space left on device"):
        write_image_pair(first, pixels(0, 3), second, pixels(1, 1))
    if first_existed:
        assert first.read_bytes() == b"the previous render"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["r.png"]
    else:
        assert list(tmp_path.iterdir()) == []
