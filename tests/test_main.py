"""The entry point refuses a busy workspace before loading torch, with the lock's own line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from avatarperfect_cli.io.workspace import workspace_lock

# Runs the entry point as `avatarperfect ARGS` would, then reports whether torch was loaded and the exit status.
PROBE = """
import sys
from avatarperfect_cli.__main__ import main
sys.argv = ["avatarperfect", *sys.argv[1:]]
try:
    main()
except SystemExit as exit:
    print("torch" in sys.modules, exit.code)
"""


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", PROBE, *args], capture_output=True, text=True, timeout=300)


def test_a_busy_workspace_is_refused_before_torch_loads(tmp_path: Path) -> None:
    workspace = tmp_path / "ws"
    workspace.mkdir()
    with workspace_lock(workspace):
        result = _run("refine", "--iterations", "5", str(workspace))
    assert result.stdout.split() == ["False", "2"]
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "another avatarperfect stage" in lines[0] and str(workspace) in lines[0]


def test_a_free_workspace_goes_on_to_the_cli(tmp_path: Path) -> None:
    workspace = tmp_path / "ws"
    workspace.mkdir()
    with workspace_lock(workspace):
        pass  # a lock that was held and released
    result = _run("refine", str(workspace))
    # the CLI itself ran (torch loaded) and refused an empty folder as a workspace, in one line
    assert result.stdout.split() == ["True", "2"]
    assert "another avatarperfect stage" not in result.stderr and len(result.stderr.strip().splitlines()) == 1
