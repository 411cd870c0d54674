"""Interrupt signals become KeyboardInterrupt only in the package's own code; the CLI reports them."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from avatarperfect_cli import interrupts
from avatarperfect_cli.io.workspace import lock_path


@pytest.fixture()
def routed():
    saved = {signum: signal.getsignal(signum) for signum in (*interrupts.SIGNALS, signal.SIGALRM)}
    interrupts.install()
    yield
    signal.setitimer(signal.ITIMER_REAL, 0.0)
    for signum, handler in saved.items():
        signal.signal(signum, handler)
    interrupts._received.clear()


def test_a_signal_during_an_import_waits_until_the_import_is_done(routed, tmp_path: Path, monkeypatch) -> None:
    """A signal delivered inside an import does not break it; KeyboardInterrupt comes right after, outside."""
    (tmp_path / "slow_module.py").write_text(
        "import os, signal, time\n"
        "os.kill(os.getpid(), signal.SIGTERM)\n"
        "end = time.monotonic() + 0.3\n"
        "while time.monotonic() < end:\n"
        "    pass\n"
        "COMPLETE = True\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "slow_module", raising=False)
    deadline = time.monotonic() + 10.0
    with pytest.raises(KeyboardInterrupt):
        import slow_module  # noqa: F401

        while time.monotonic() < deadline:
            time.sleep(0.001)  # the next poll lands here, outside any import
    assert interrupts.received() and sys.modules["slow_module"].COMPLETE


def test_a_pending_signal_stops_a_stage_before_it_takes_the_workspace(routed, tmp_path: Path) -> None:
    from avatarperfect_cli.io.workspace import workspace_lock

    interrupts._received.append(signal.SIGTERM)  # as if deferred through the start-up imports
    with pytest.raises(KeyboardInterrupt):
        with workspace_lock(tmp_path / "ws"):
            pass
    assert not lock_path(tmp_path / "ws").exists()


def test_plain_code_is_safe_an_import_is_not(tmp_path: Path, monkeypatch) -> None:
    assert interrupts._safe(sys._getframe())
    (tmp_path / "frame_module.py").write_text("import sys\nFRAME = sys._getframe()\n")  # its body runs in an import
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "frame_module", raising=False)
    import frame_module

    assert not interrupts._safe(frame_module.FRAME)


def _routes_sigalrm(pid: int) -> bool:
    """Whether process `pid` catches SIGALRM, i.e. has run `interrupts.install` (Python itself does not)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:  # it has ended
        return False
    caught = int(next(line.split()[1] for line in status.splitlines() if line.startswith("SigCgt:")), 16)
    return bool(caught >> (signal.SIGALRM - 1) & 1)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_an_interrupt_during_the_imports_ends_in_one_line_and_130(tmp_path: Path, signum: int) -> None:
    """The signal at moments through the heavy imports and the start of a command, once the entry point has
    routed it: never status 1 or a traceback."""
    for delay in (0.0, 0.1, 0.3, 0.8):
        process = subprocess.Popen(
            [sys.executable, "-m", "avatarperfect_cli", "visibility", str(tmp_path / "missing")],
            stderr=subprocess.PIPE, text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )  # fmt: skip
        while process.poll() is None and not _routes_sigalrm(process.pid):
            time.sleep(0.001)
        time.sleep(delay)
        process.send_signal(signum)
        _, stderr = process.communicate(timeout=120)
        assert "Traceback" not in stderr, stderr
        if process.returncode == 2:  # it had already refused the missing workspace
            assert "not a workspace" in stderr
            continue
        assert (process.returncode, stderr.strip().splitlines()) == (130, ["interrupted: nothing was changed"]), delay
