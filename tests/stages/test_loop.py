"""`avatarperfect loop` end to end on the committed 256² sample shrunk to 64², with a simulated person as its
editor (simulated_person.py): a painting saved in two halves is registered only once whole, an unchanged save or
an `s` refines without an edit, a save over suggested.png is moved aside, and a bad option changes nothing."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from avatarperfect_cli.cli import app
from tests.stages.test_refinement_stages import SAMPLE, invoke, snapshot, trained, workspace  # noqa: F401 (fixtures)

PERSON = Path(__file__).resolve().parent / "simulated_person.py"
FAST_LOOP = ["--iterations", "8", "--starts", "1", "--steps", "3", "--resolution", "32"]


def person(modes: str) -> str:
    return f"{sys.executable} {PERSON} {SAMPLE} {modes}"


def refines(root: Path) -> list[dict]:
    return [entry for entry in json.loads((root / "workspace.json").read_text())["history"] if entry["stage"] == "refine"]


def test_two_rounds_register_the_whole_painting_only_and_refine_an_unchanged_one_without_an_edit(workspace: Path):
    result = invoke("loop", workspace, "--rounds", "2", "--editor", person("half-first,unchanged"), *FAST_LOOP)
    assert result.exit_code == 0, result.output
    log = result.stderr
    painted = workspace / "suggestions" / "001" / "painted.png"
    assert f"{painted} is not a whole image yet" in log.replace("\n", "")  # the half was seen and left alone
    assert "cannot register" not in log and "error" not in log
    assert sorted(p.name for p in (workspace / "edits").iterdir()) == ["001"]
    assert (workspace / "edits" / "001" / "edited.png").read_bytes() == painted.read_bytes()
    assert "painted.png is the suggestion unchanged" in log
    assert [(entry["avatar"], entry["edits"]) for entry in refines(workspace)] == [(1, [1]), (2, [1])]
    for name in ("suggestions/001/guide.png", "suggestions/002/suggested.png", "visibility/001.png", "avatar/002.ply"):
        assert (workspace / name).is_file(), name
    assert "round 2 of 2 done" in log
    evaluated = invoke("evaluate", workspace, "--test", SAMPLE / "test", "--frames", "0:19:10")
    assert evaluated.exit_code == 0, evaluated.output
    metrics = json.loads((workspace / "eval" / "002" / "test" / "metrics.json").read_text())["mean"]
    assert all(math.isfinite(metrics[key]) for key in ("psnr", "iou", "ssim")), metrics


def test_a_painting_saved_over_the_suggestion_is_moved_aside_and_registered(workspace: Path):
    result = invoke("loop", workspace, "--rounds", "1", "--editor", person("overwrite"), *FAST_LOOP)
    assert result.exit_code == 0, result.output
    folder = workspace / "suggestions" / "001"
    edit = workspace / "edits" / "001"
    assert (edit / "edited.png").read_bytes() == (folder / "painted.png").read_bytes()
    assert (folder / "painted.png").read_bytes() != (folder / "suggested.png").read_bytes()
    assert json.loads((edit / "edit.json").read_text())["pixels"]["edited"] > 0
    assert [entry["edits"] for entry in refines(workspace)] == [[1]]


def test_s_skips_the_painting_and_refines(workspace: Path, tmp_path: Path):
    arguments = ["loop", workspace, "--rounds", "1", "--painted", tmp_path / "mine.png", *FAST_LOOP]
    result = CliRunner().invoke(app, [str(a) for a in arguments], input="s\n")
    assert result.exit_code == 0, result.output
    assert "skipped" in result.stderr
    assert not (workspace / "edits").exists()
    assert [(entry["avatar"], entry["edits"]) for entry in refines(workspace)] == [(1, [])]


@pytest.mark.parametrize(
    ("option", "finding"),
    [(["--editor", "no-such-editor-here"], "no such program"), (["--rounds", "0"], "--rounds"), (["--painted", "nowhere/x.png"], "folder")],
)
def test_a_bad_option_is_one_line_and_changes_nothing(workspace: Path, option: list[str], finding: str):
    before = snapshot(workspace)
    result = invoke("loop", workspace, *option)
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and finding in lines[0], result.stderr
    assert snapshot(workspace) == before
