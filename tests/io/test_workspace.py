"""Workspace creation is all-or-nothing; bad folders give one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.io.workspace import MANIFEST, new_workspace, open_workspace


def test_new_workspace_appears_complete(tmp_path: Path):
    root = tmp_path / "ws"
    with new_workspace(root, {"iteration": 0, "dataset": "d"}) as staged:
        assert not root.exists()
        staged.avatar_path(0).parent.mkdir(parents=True)
        staged.avatar_path(0).write_text("ply")
    workspace = open_workspace(root)
    assert workspace.iteration == 0 and workspace.manifest["dataset"] == "d"
    assert workspace.avatar_path().read_text() == "ply"
    assert [p.name for p in tmp_path.iterdir()] == ["ws"]


def test_interrupted_creation_leaves_nothing(tmp_path: Path):
    root = tmp_path / "ws"
    with pytest.raises(KeyboardInterrupt):
        with new_workspace(root, {"iteration": 0}) as staged:
            staged.avatar_path(0).parent.mkdir(parents=True)
            raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_existing_workspace_needs_force_and_is_kept_on_failure(tmp_path: Path):
    root = tmp_path / "ws"
    with new_workspace(root, {"iteration": 0, "tag": "old"}):
        pass
    with pytest.raises(AvatarPerfectError, match="--force"):
        with new_workspace(root, {"iteration": 0}):
            pass
    with pytest.raises(RuntimeError):
        with new_workspace(root, {"iteration": 0, "tag": "new"}, force=True):
            raise RuntimeError("boom")
    assert open_workspace(root).manifest["tag"] == "old"
    with new_workspace(root, {"iteration": 0, "tag": "new"}, force=True):
        pass
    assert open_workspace(root).manifest["tag"] == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["ws"]


def test_refuses_a_folder_that_is_not_a_workspace(tmp_path: Path):
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "a.jpg").write_text("x")
    with pytest.raises(AvatarPerfectError, match="not a workspace"):
        with new_workspace(tmp_path / "photos", {"iteration": 0}, force=True):
            pass


def test_open_errors(tmp_path: Path):
    with pytest.raises(AvatarPerfectError, match="train-initial"):
        open_workspace(tmp_path)
    (tmp_path / MANIFEST).write_text("{broken")
    with pytest.raises(InputFileError, match="unreadable manifest"):
        open_workspace(tmp_path)
    (tmp_path / MANIFEST).write_text(json.dumps({"format": "something else"}))
    with pytest.raises(InputFileError, match="not an avatarperfect manifest"):
        open_workspace(tmp_path)


def test_missing_avatar_is_named(tmp_path: Path):
    with new_workspace(tmp_path / "ws", {"iteration": 3}):
        pass
    with pytest.raises(AvatarPerfectError, match="iteration 3"):
        open_workspace(tmp_path / "ws").require_avatar()
