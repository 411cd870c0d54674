"""Workspace creation is all-or-nothing; bad folders give one-line errors."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.io.workspace import MANIFEST, locked_workspace, new_workspace, open_workspace, workspace_lock


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


def _hold_lock(root: str, ready, release) -> None:
    from avatarperfect_cli.io.workspace import workspace_lock

    with workspace_lock(Path(root)):
        ready.set()
        release.wait(10)


def test_second_stage_is_refused_while_the_lock_is_held(tmp_path: Path):
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    ready, release = context.Event(), context.Event()
    holder = context.Process(target=_hold_lock, args=(str(tmp_path / "ws"), ready, release))
    holder.start()
    try:
        assert ready.wait(20)
        with pytest.raises(AvatarPerfectError, match=f"pid {holder.pid}"):
            with workspace_lock(tmp_path / "ws"):
                pass
    finally:
        release.set()
        holder.join(10)
    with workspace_lock(tmp_path / "ws"):  # released when its process ended
        pass


def test_a_killed_holder_leaves_no_stale_lock(tmp_path: Path):
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    ready, release = context.Event(), context.Event()
    holder = context.Process(target=_hold_lock, args=(str(tmp_path / "ws"), ready, release))
    holder.start()
    assert ready.wait(20)
    holder.kill()
    holder.join(10)
    with workspace_lock(tmp_path / "ws"):
        pass


def test_a_read_only_command_removes_what_a_stage_killed_before_its_workspace_left(tmp_path: Path):
    """A train-initial killed hard while saving leaves `.ws.lock`, its staging folder and no workspace;
    `apply-edit --list` refuses the missing workspace and removes both, unless a running stage holds the lock."""
    from avatarperfect_cli.io.workspace import lock_path, reading_workspace

    with workspace_lock(tmp_path / "ws"):  # held by a running stage: its lock file and staging folder stay
        (tmp_path / ".ws.abcd1234.tmp" / "avatar").mkdir(parents=True)
        with pytest.raises(AvatarPerfectError, match="ws"), reading_workspace(tmp_path / "ws"):
            pass
        assert lock_path(tmp_path / "ws").exists() and (tmp_path / ".ws.abcd1234.tmp").exists()
        (tmp_path / "unrelated.lock").write_text("")
    lock_path(tmp_path / "ws").write_text("12345\n")  # what a stage killed while saving leaves
    (tmp_path / ".ws.abcd1234.tmp" / "avatar").mkdir(parents=True, exist_ok=True)
    with pytest.raises(AvatarPerfectError, match="ws"), reading_workspace(tmp_path / "ws"):
        pass
    assert sorted(p.name for p in tmp_path.iterdir()) == ["unrelated.lock"]


def test_lock_cleans_what_a_killed_stage_left(tmp_path: Path):
    root = tmp_path / "ws"
    with new_workspace(root, {"iteration": 0, "history": [{"stage": "train-initial", "avatar": 0}]}) as staged:
        (staged.root / "avatar").mkdir()
        (staged.root / "avatar" / "000.ply").write_text("ply")
    (root / "avatar" / "001.ply").write_text("written but never committed")
    (root / "avatar" / ".001.tmp-1a2b3c4d.ply").write_text("half")
    (tmp_path / ".ws.abcd.tmp").mkdir()  # a killed train-initial's staging folder
    with locked_workspace(root) as workspace:
        assert workspace.committed_avatars() == {0}
    assert sorted(p.name for p in (root / "avatar").iterdir()) == ["000.ply"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ws"]


def test_a_retired_workspace_is_put_back(tmp_path: Path):
    """A crash between the two renames of the fallback replace leaves the old workspace retired."""
    root = tmp_path / "ws"
    with new_workspace(root, {"iteration": 0, "tag": "old"}):
        pass
    os.replace(root, tmp_path / ".ws.retired.tmp")
    with locked_workspace(root) as workspace:
        assert workspace.manifest["tag"] == "old"


def test_force_swaps_in_one_step(tmp_path: Path, monkeypatch):
    """With --force the old workspace is exchanged for the new one: at no moment is the path missing."""
    from avatarperfect_cli.io import atomic

    root = tmp_path / "ws"
    with new_workspace(root, {"iteration": 0, "tag": "old"}):
        pass
    seen = []
    exchange = atomic._exchange

    def watched(first: Path, second: Path) -> bool:
        swapped = exchange(first, second)
        seen.append((swapped, json.loads((root / MANIFEST).read_text())["tag"]))
        return swapped

    monkeypatch.setattr(atomic, "_exchange", watched)
    with new_workspace(root, {"iteration": 0, "tag": "new"}, force=True):
        pass
    assert seen == [(True, "new")]
    assert open_workspace(root).manifest["tag"] == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["ws"]


def test_numbered_folders_count_up_and_skip_staging(tmp_path: Path):
    with new_workspace(tmp_path / "ws", {"iteration": 0}):
        pass
    workspace = open_workspace(tmp_path / "ws")
    assert workspace.next_numbered_folder("edits").name == "001"
    (workspace.root / "edits" / "002").mkdir(parents=True)
    (workspace.root / "edits" / ".003.x.tmp").mkdir()
    assert [p.name for p in workspace.numbered_folders("edits")] == ["002"]
    assert workspace.next_numbered_folder("edits").name == "003"


def test_a_lock_that_cannot_be_created_is_one_line_and_reading_needs_none(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """A workspace whose parent folder is read-only: a writing stage refuses in one line; a read-only one reads it."""
    from avatarperfect_cli.io import workspace as module

    root = tmp_path / "ws"
    with new_workspace(root, {"iteration": 0, "history": []}):
        pass
    real_open = os.open

    def refusing_open(path, flags, *args):
        if str(path).endswith(".ws.lock") and flags & os.O_CREAT:
            raise PermissionError(13, "Permission denied")
        return real_open(path, flags, *args)

    monkeypatch.setattr(module.os, "open", refusing_open)
    with pytest.raises(AvatarPerfectError, match="cannot create the workspace's lock file") as error:
        with locked_workspace(root):
            pass
    assert "\n" not in str(error.value)
    with module.reading_workspace(root) as workspace:
        assert workspace.iteration == 0


def test_reading_a_busy_workspace_needs_no_lock(tmp_path: Path):
    root = tmp_path / "ws"
    with new_workspace(root, {"iteration": 0}):
        pass
    with workspace_lock(root):
        with pytest.raises(AvatarPerfectError, match="another avatarperfect stage"):
            with locked_workspace(root):
                pass
        from avatarperfect_cli.io.workspace import reading_workspace

        with reading_workspace(root) as workspace:
            assert workspace.iteration == 0


def test_a_lock_for_a_missing_workspace_leaves_no_folder(tmp_path: Path):
    with pytest.raises(AvatarPerfectError, match="not a workspace"):
        with locked_workspace(tmp_path / "no" / "such" / "ws"):
            pass
    assert list(tmp_path.iterdir()) == []
