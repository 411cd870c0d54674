"""Ctrl-C and SIGTERM, raised as KeyboardInterrupt only where avatarperfect's own code runs.

Python raises KeyboardInterrupt wherever the main thread happens to be. Inside an import (numpy's lazy
attributes) or numba's compiler callbacks that exception is swallowed or turned into another one, and
the stage then ends with a traceback and status 1, or runs on. Here the signal is recorded, and
KeyboardInterrupt is raised at once where that is safe: in this package's own code, or anywhere no
import, numba or command-line framework frame is on the stack; otherwise the check repeats every POLL_S
seconds. Every write of
a stage is atomic, so raising anywhere in our own code is safe.
"""

from __future__ import annotations

import atexit
import os
import signal
from pathlib import Path
from types import FrameType

PACKAGE = str(Path(__file__).resolve().parent)
POLL_S = 0.02
# frames an exception must not start in: imports, numba's callbacks, and the command line's framework
# (typer ends a KeyboardInterrupt of its own with status 130 and no message)
UNSAFE = ("importlib._bootstrap", *(f"{os.sep}{package}{os.sep}" for package in ("numba", "click", "typer")))
SIGNALS = (signal.SIGINT, signal.SIGTERM)
_received: list[int] = []  # the signals seen, in order
_finished: list[bool] = []  # non-empty once the command is over: signals are only recorded


def install(signals: tuple[int, ...] = SIGNALS) -> None:
    """Route `signals` here (main thread only), except one the parent set to be ignored (a background
    job's Ctrl-C); a signal already routed here stays so."""
    for signum in signals:
        if signal.getsignal(signum) is not signal.SIG_IGN:
            signal.signal(signum, on_signal)
    if signal.getsignal(signal.SIGALRM) is not _on_poll:
        signal.signal(signal.SIGALRM, _on_poll)
        atexit.register(_stop_polling)  # Python restores SIGALRM's default (terminate) as it exits


def received() -> bool:
    """Whether an interrupt signal has arrived since `install`."""
    return bool(_received)


def check() -> None:
    """Raise KeyboardInterrupt if a signal arrived and is still pending: called before a stage takes its
    workspace, so a signal deferred through the start-up imports stops a stage too short to be polled."""
    if _received and not _finished:
        _stop_polling()
        raise KeyboardInterrupt


def finish() -> None:
    """The command is over (the process is exiting): from now on a signal is only recorded, so none
    raises inside the interpreter's exit handlers."""
    _finished.append(True)
    _stop_polling()


def on_signal(signum: int, frame: FrameType | None) -> None:
    _received.append(signum)
    if not _finished:
        _raise_in_own_code(frame)


def _on_poll(signum: int, frame: FrameType | None) -> None:
    if _received and not _finished:
        _raise_in_own_code(frame)


def _stop_polling() -> None:
    signal.setitimer(signal.ITIMER_REAL, 0.0)


def _raise_in_own_code(frame: FrameType | None) -> None:
    if frame is not None and _safe(frame):
        _stop_polling()
        raise KeyboardInterrupt
    signal.setitimer(signal.ITIMER_REAL, POLL_S)  # look again shortly


def _safe(frame: FrameType) -> bool:
    """Whether KeyboardInterrupt may start in `frame`: our own code, or a stack without an UNSAFE frame."""
    if frame.f_code.co_filename.startswith(PACKAGE):
        return True
    current: FrameType | None = frame
    while current is not None:
        if any(part in current.f_code.co_filename for part in UNSAFE):
            return False
        current = current.f_back
    return True
