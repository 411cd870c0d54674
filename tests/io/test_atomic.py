import os
from pathlib import Path

import pytest

from avatarperfect_cli.io.atomic import atomic_path, atomic_write_bytes, atomic_write_text, staging_dir


def test_success_replaces_target_and_leaves_no_temporary(tmp_path: Path) -> None:
    target = tmp_path / "render.png"
    target.write_text("old")
    with atomic_path(target) as temporary:
        assert temporary.parent == target.parent
        assert temporary.suffix == ".png"
        assert temporary != target
        temporary.write_text("new")
        assert target.read_text() == "old"  # not visible before the block ends
    assert target.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["render.png"]


@pytest.mark.parametrize("error", [RuntimeError("boom"), KeyboardInterrupt()])
def test_error_keeps_old_file_and_removes_temporary(tmp_path: Path, error: BaseException) -> None:
    target = tmp_path / "avatar.ply"
    target.write_text("old")
    with pytest.raises(type(error)):
        with atomic_path(target) as temporary:
            temporary.write_text("half written")
            raise error
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["avatar.ply"]


def test_error_before_anything_is_written(tmp_path: Path) -> None:
    with pytest.raises(ValueError):
        with atomic_path(tmp_path / "a.txt"):
            raise ValueError
    assert list(tmp_path.iterdir()) == []


def test_creates_parent_folders(tmp_path: Path) -> None:
    target = tmp_path / "ws" / "suggest" / "001" / "pose.json"
    atomic_write_text(target, "{}")
    assert target.read_text() == "{}"


def test_write_bytes_and_text(tmp_path: Path) -> None:
    atomic_write_bytes(tmp_path / "a.bin", b"\x00\xff")
    atomic_write_text(tmp_path / "b.txt", "é")
    assert (tmp_path / "a.bin").read_bytes() == b"\x00\xff"
    assert (tmp_path / "b.txt").read_bytes() == "é".encode()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin", "b.txt"]


def test_staging_dir_has_ordinary_permissions(tmp_path: Path) -> None:
    plain = tmp_path / "plain"
    plain.mkdir()
    staged = staging_dir(tmp_path / "ws")
    assert staged.parent == tmp_path and staged.name.startswith(".ws.") and not any(staged.iterdir())
    assert os.stat(staged).st_mode & 0o777 == os.stat(plain).st_mode & 0o777
