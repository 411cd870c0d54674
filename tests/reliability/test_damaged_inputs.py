"""Every input class through the damaged-input corpus (corpus.py), by the real CLI.

Each case must end with exactly one line on stderr ("error: ..." naming the damaged file), exit status 2, no
traceback, its input files byte-identical, and no new file besides a workspace's lock file. The cases run
in-process (typer's CliRunner) to stay fast; SUBPROCESS_CASES also run as a separate `python -m
avatarperfect_cli` process, where stray library output on the real stderr would show.
"""

from __future__ import annotations

import hashlib
import re
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from avatarperfect_cli.cli import app
from tests.reliability.corpus import CASES, Case

LOCK_FILE = re.compile(r"\.[^/]+\.lock")  # a workspace's lock, a hidden sibling (io/workspace.py)
SUBPROCESS_CASES = [
    "ply/fewer vertices declared", "motion/single .npy", "dataset/image truncated", "workspace/camera fx zero",
    "prepare/empty .mp4", "prepare/text .mp4", "edit-png/10000x10000 header", "report/output an existing file",
]  # fmt: skip
CASES_BY_NAME = {case.name: case for case in CASES}


def snapshot(root: Path) -> dict[str, str]:
    """Relative path -> sha256 of every file ("folder" for folders) under `root`."""
    return {
        str(path.relative_to(root)): "folder" if path.is_dir() else hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(root.rglob("*"))
    }


def check_failure(case: Case, root: Path, damaged: Path, before: dict[str, str], exit_code: int, stderr: str) -> None:
    lines = stderr.strip().splitlines()
    assert exit_code == 2, f"{case.name}: exit {exit_code}, stderr:\n{stderr}"
    assert len(lines) == 1, f"{case.name}: {len(lines)} lines on stderr:\n{stderr}"
    message = lines[0]
    assert message.startswith("error: ") and "Traceback" not in stderr
    if case.names is not None:
        assert case.names in message, f"{case.name}: the message does not quote {case.names!r}: {message}"
    else:
        assert damaged.name in message and str(root) in message, f"{case.name}: the message does not name {damaged}: {message}"
    after = snapshot(root)
    assert {path: after.get(path) for path in before} == before, f"{case.name}: an input file changed"
    new = [path for path in after if path not in before]
    assert all(LOCK_FILE.fullmatch(Path(path).name) for path in new), f"{case.name}: wrote {new}"


def test_corpus_covers_every_damage_of_the_issue():
    """Guards the corpus itself: at least the kinds of damage the issue lists, for every input class."""
    names = " ".join(CASES_BY_NAME)
    for kind in ("truncated", "empty", "folder", "NaN", "Inf", "missing", "strings", "huge", "fx zero", "fy negative", "rotation"):
        assert kind in names, kind
    assert {case.name.split("/")[0] for case in CASES} >= {"ply", "camera-json", "pose-json", "motion", "dataset", "workspace"}


@pytest.mark.parametrize("case", CASES, ids=[case.name for case in CASES])
def test_damaged_input_is_one_line_exit_2_and_changes_nothing(case: Case, tmp_path: Path):
    damaged = case.make_files(tmp_path)
    before = snapshot(tmp_path)
    result = CliRunner().invoke(app, case.argv(tmp_path))
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise result.exception  # a traceback the user would see: show it
    check_failure(case, tmp_path, damaged, before, result.exit_code, result.stderr)


@pytest.mark.parametrize("name", SUBPROCESS_CASES)
def test_damaged_input_in_a_real_process(name: str, tmp_path: Path):
    case = CASES_BY_NAME[name]
    damaged = case.make_files(tmp_path)
    before = snapshot(tmp_path)
    command = [sys.executable, "-m", "avatarperfect_cli", *case.argv(tmp_path)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120)
    check_failure(case, tmp_path, damaged, before, result.returncode, result.stderr)
