"""Third-party libraries' own output kept off the user's stderr: FFmpeg (through OpenCV), TFLite and absl (through
MediaPipe) write to the process's file descriptor 2 from C++, and Pillow and others issue Python warnings or log
records. While a command runs (unless `--verbose`), descriptor 2 goes to /dev/null and Python's `sys.stderr`, which
carries the command's own lines (progress, notes, the one-line error), to a copy of the original descriptor.
"""

from __future__ import annotations

import logging
import os
import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def libraries_quiet() -> Iterator[None]:
    """Silence the libraries' native stderr, Python warnings and log records for the block (see the module doc)."""
    with warnings.catch_warnings(), _native_stderr_discarded():
        warnings.simplefilter("ignore")
        logging.disable(logging.CRITICAL)
        try:
            yield
        finally:
            logging.disable(logging.NOTSET)


@contextmanager
def _native_stderr_discarded() -> Iterator[None]:
    """Point descriptor 2 at /dev/null; a `sys.stderr` that wrote to it writes to a copy of it meanwhile."""
    stream = sys.stderr
    try:
        stream.flush()
        writes_to_descriptor_2 = stream.fileno() == 2
    except (AttributeError, OSError, ValueError):  # e.g. a test runner's capture
        writes_to_descriptor_2 = False
    original = os.dup(2)
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 2)
    os.close(null)
    copy = None
    if writes_to_descriptor_2:
        copy = open(original, "w", buffering=1, encoding=stream.encoding, errors=stream.errors, closefd=False)
        sys.stderr = copy
    try:
        yield
    finally:
        if copy is not None:
            copy.flush()
            sys.stderr = stream
            copy.close()
        os.dup2(original, 2)
        os.close(original)
