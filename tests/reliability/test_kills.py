"""Every workspace-writing stage killed at random moments (kill_harness.py), two stages on one workspace, and a
killed frames render.

KILLS kills per stage (default 1: the fast subset; the signals rotate over the stages), SEED draws the moments
(default 0), KILL_REPORT=path.json collects the counts. `make reliability` runs the full run (KILLS=50).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from avatarperfect_cli.io.workspace import lock_path
from tests.reliability.kill_harness import (
    default_sigint,
    SAMPLE,
    STAGES,
    STAGES_BY_NAME,
    WS,
    Harness,
    Outcome,
    invoke,
    snapshot,
    summarise,
    write_results,
)

KILLS = int(os.environ.get("KILLS", "1"))
SEED = int(os.environ.get("SEED", "0"))
REPORT = os.environ.get("KILL_REPORT")
CLI = [sys.executable, "-m", "avatarperfect_cli"]


@pytest.fixture(scope="module")
def harness(tmp_path_factory) -> Harness:
    return Harness(tmp_path_factory.mktemp("kills"))


@pytest.mark.parametrize("stage", [stage.name for stage in STAGES])
def test_a_killed_stage_leaves_the_old_or_the_new_workspace(harness: Harness, stage: str):
    outcomes = harness.kill_stage(stage, KILLS, SEED)
    if REPORT:
        write_results(Path(REPORT), stage, summarise(outcomes))
    failures = [
        f"{o.signal} in {o.phase} at {o.moment}: exit {o.exit_status}, {o.state}: {'; '.join(o.problems)}\n{o.stderr_tail}"
        for o in outcomes
        if o.problems
    ]
    assert not failures, "\n".join(failures)


def _copy(harness: Harness, stage: str, folder: Path) -> Path:
    """A private copy of `stage`'s finished workspace at folder/box/ws."""
    workspace = folder / "box" / WS
    shutil.copytree(harness.reference(stage).workspace, workspace)
    return workspace


def _wait_for(condition: Callable[[], bool], process: subprocess.Popen, timeout: float = 300.0) -> None:
    end = time.perf_counter() + timeout
    while not condition():
        assert process.poll() is None, "the process ended before the awaited moment"
        assert time.perf_counter() < end, "timed out"
        time.sleep(0.005)


def test_a_second_stage_on_the_workspace_refuses_at_once(harness: Harness, tmp_path: Path):
    """While `train-initial --force` retrains a workspace (holding its lock), `visibility` and `refine` each refuse
    in one line, before any work (the holder is still running when they have answered), and change nothing."""
    workspace = _copy(harness, "train-initial", tmp_path)
    before = snapshot(workspace)
    log = tmp_path / "holder.txt"
    retrain = ["train-initial", str(SAMPLE / "train"), str(workspace), "--resolution", "64", "--iterations", "100000", "--force"]
    with open(log, "wb") as holder_stderr:
        holder = subprocess.Popen([*CLI, *retrain], stderr=holder_stderr, preexec_fn=default_sigint)
    try:
        _wait_for(lock_path(workspace).exists, holder)
        seconds = {}
        for second in (["visibility", str(workspace)], ["refine", str(workspace)]):
            start = time.perf_counter()
            result = subprocess.run([*CLI, *second], capture_output=True, text=True, timeout=300)
            seconds[second[0]] = round(time.perf_counter() - start, 2)
            assert holder.poll() is None, "the holder finished first: the test proves nothing"
            lines = result.stderr.strip().splitlines()
            assert result.returncode == 2 and len(lines) == 1, result.stderr
            assert "another avatarperfect stage" in lines[0] and str(holder.pid) in lines[0]
    finally:
        holder.send_signal(signal.SIGINT)
        try:
            status = holder.wait(timeout=120)
        except subprocess.TimeoutExpired:
            holder.kill()
            holder.wait()
            raise AssertionError(f"the holder ignored SIGINT for 120 s:\n{log.read_text()}") from None
    assert status == 130, log.read_text()
    assert invoke("apply-edit", workspace, "--list").exit_code == 0
    assert snapshot(workspace) == before and sorted(p.name for p in workspace.parent.iterdir()) == [WS]
    print(f"refusal took {seconds} s (wall, from starting the process to its exit)")
    if REPORT:
        write_results(Path(REPORT), "concurrent refusal seconds", seconds)


def test_a_killed_frames_render_leaves_nothing_after_the_next_render(harness: Harness, tmp_path: Path):
    workspace = harness.reference("train-initial").workspace
    out = tmp_path / "frames"
    render = subprocess.Popen(
        [*CLI, "render", str(workspace), "--turntable", "500", "-o", str(out)], stderr=subprocess.DEVNULL, preexec_fn=default_sigint
    )
    _wait_for(lambda: any(tmp_path.glob(".frames.*.tmp/frame_0001.png")), render)
    render.send_signal(signal.SIGKILL)
    render.wait(timeout=60)
    assert [p.name for p in tmp_path.iterdir()] != ["frames"]  # the staging folder is there
    result = invoke("render", workspace, "--turntable", "2", "-o", out)
    assert result.exit_code == 0, result.output
    assert [p.name for p in tmp_path.iterdir()] == ["frames"]
    assert sorted(p.name for p in out.iterdir()) == ["frame_0000.png", "frame_0001.png"]


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


DAMAGES: dict[str, tuple[Callable[[Path], None], str]] = {
    "a stray hidden file": (lambda ws: (ws / "edits" / ".stray").write_text("x"), "left after the next command"),
    "an edit's mask missing": (lambda ws: (ws / "edits" / "001" / "mask.png").unlink(), "neither the old nor the new"),
    "the manifest truncated": (lambda ws: _truncate(ws / "workspace.json"), "manifest does not load"),
    "the new avatar truncated": (lambda ws: _truncate(ws / "avatar" / "001.ply"), "does not load"),
}


@pytest.mark.parametrize("damage", list(DAMAGES))
def test_the_checks_catch_a_damaged_workspace(harness: Harness, tmp_path: Path, damage: str):
    """The harness's own checks: the finished workspace of `refine` passes as its new state; each damage is caught."""
    stage = STAGES_BY_NAME["refine"]
    reference = harness.reference(stage.name)
    intact = Outcome(stage.name, "SIGINT", "run", 1.0, True, 130, "lost")
    harness.check(stage, intact, _copy(harness, stage.name, tmp_path / "intact"), reference.before, tmp_path)
    assert (intact.state, intact.problems) == ("new", [])
    workspace = _copy(harness, stage.name, tmp_path / "damaged")
    make_damage, finding = DAMAGES[damage]
    make_damage(workspace)
    outcome = Outcome(stage.name, "SIGINT", "run", 1.0, True, 130, "lost")
    harness.check(stage, outcome, workspace, reference.before, tmp_path)
    assert any(finding in problem for problem in outcome.problems), outcome.problems
    assert outcome.state != "new" or damage == "a stray hidden file"


def test_the_checks_catch_a_wrong_exit_status(harness: Harness, tmp_path: Path):
    stage = STAGES_BY_NAME["refine"]
    outcome = Outcome(stage.name, "SIGTERM", "run", 1.0, True, 1, "lost")
    harness.check(stage, outcome, _copy(harness, stage.name, tmp_path), harness.reference(stage.name).before, tmp_path)
    assert outcome.state == "new" and outcome.problems == ["exit status 1 after SIGTERM"]
