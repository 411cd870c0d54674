"""Ctrl-C and SIGTERM, raised as KeyboardInterrupt only where avatarperfect's own code runs.

Python raises KeyboardInterrupt wherever the main thread happens to be. Inside numpy's lazy imports or
numba's compiler callbacks that exception is swallowed or turned into another one, and the stage then
ends with a traceback and status 1, or runs on. Here the signal is recorded, and KeyboardInterrupt is
raised once the interrupted frame belongs to this package (checked again every POLL_S seconds until it
does). Every write of a stage is atomic, so raising anywhere in our own code is safe.
"""

from __future__ import annotations

import atexit
import signal
from pathlib import Path
from types import FrameType

PACKAGE = str(Path(__file__).resolve().parent)
POLL_S = 0.02
SIGNALS = (signal.SIGINT, signal.SIGTERM)
_received: list[int] = []  # the signals seen, in order


def install(signals: tuple[int, ...] = SIGNALS) -> None:
    """Route `signals` here (main thread only), except one the parent set to be ignored (a background
    job's Ctrl-C); a signal already routed here stays so."""
    for signum in signals:
        if signal.getsignal(signum) is not signal.SIG_IGN:
            signal.signal(signum, on_signal)
    signal.signal(signal.SIGALRM, _on_poll)
    atexit.register(_stop_polling)  # Python restores SIGALRM's default (terminate) as it exits


def received() -> bool:
    """Whether an interrupt signal has arrived since `install`."""
    return bool(_received)


def on_signal(signum: int, frame: FrameType | None) -> None:
    _received.append(signum)
    _raise_in_own_code(frame)


def _on_poll(signum: int, frame: FrameType | None) -> None:
    if _received:
        _raise_in_own_code(frame)


def _stop_polling() -> None:
    signal.setitimer(signal.ITIMER_REAL, 0.0)


def _raise_in_own_code(frame: FrameType | None) -> None:
    if frame is not None and frame.f_code.co_filename.startswith(PACKAGE):
        _stop_polling()
        raise KeyboardInterrupt
    signal.setitimer(signal.ITIMER_REAL, POLL_S)  # not ours: look again shortly
