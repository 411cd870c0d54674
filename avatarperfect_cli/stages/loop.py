"""The `loop` command: rounds of suggest, paint, apply-edit and refine for a person at an image editor.

Each round runs the existing stages one after another, each taking and releasing the workspace's lock:
`suggest` (which first brings ws/visibility/NNN up to date), then it waits for the painting, registers it
with `apply-edit` and runs `refine`. While it waits no lock is held and nothing is written.

The painting is a new image file the person saves in the suggestion's folder (or the file named with
`--painted`, saved anew). A file is read only once its size and modification time stayed the same for
`settle_s` seconds and it decodes whole (`io.images.whole_image`), so a save still being written is never
registered. A painting saved over suggested.png itself is moved to painted.png and suggested.png put back
(both in one step), since the strokes are told from the original. A painting equal to the suggestion, or an
`s` typed on stdin, skips the edit: the round refines on what is registered already. Ctrl-C stops the loop;
each finished stage stays, the interrupted one changes nothing.
"""

from __future__ import annotations

import queue
import shlex
import shutil
import subprocess
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from rich.console import Console

from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.io import atomic_write_bytes
from avatarperfect_cli.io.atomic import updated_folder
from avatarperfect_cli.io.images import whole_image
from avatarperfect_cli.io.workspace import locked_workspace, open_workspace
from avatarperfect_cli.refinement.additional_training import RefineSettings
from avatarperfect_cli.stages.apply_edit import UnchangedImage, apply_edit
from avatarperfect_cli.stages.refine import refine
from avatarperfect_cli.stages.suggest import SuggestSettings, suggest
from avatarperfect_cli.stages.visibility import visibility_path

SUGGESTED = "suggested.png"
SUGGESTION_FILES = frozenset({SUGGESTED, "suggested_alpha.png", "guide.png"})  # suggest's own images
IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".webp", ".tif", ".tiff"})
Signature = tuple[int, int]  # a file's (size in bytes, modification time in ns)


@dataclass
class LoopSettings:
    """rounds: how many rounds to run; editor: a command line, started each round with the image to paint
    appended (None: the person opens it); painted: the file the person saves each round (None: any new image in
    the suggestion's folder); suggest, refine: those stages' settings; poll_s: seconds between looks at the
    files; settle_s: seconds a saved file's size and time must stay the same before it is read."""

    rounds: int = 5
    editor: str | None = None
    painted: Path | None = None
    suggest: SuggestSettings = field(default_factory=SuggestSettings)
    refine: RefineSettings = field(default_factory=RefineSettings)
    poll_s: float = 0.2
    settle_s: float = 0.6

    def check(self) -> None:
        """One-line AvatarPerfectError, naming the option, before any work."""
        if self.rounds < 1:
            raise AvatarPerfectError(f"--rounds must be at least 1, got {self.rounds}")
        if self.editor is not None:
            words = shlex.split(self.editor)
            if not words or shutil.which(words[0]) is None:
                raise AvatarPerfectError(f"--editor '{self.editor}': no such program")
        if self.painted is not None:
            if Path(self.painted).suffix.lower() not in IMAGE_SUFFIXES:
                raise AvatarPerfectError(f"--painted {self.painted}: give an image file ({', '.join(sorted(IMAGE_SUFFIXES))})")
            if not Path(self.painted).parent.is_dir():
                raise AvatarPerfectError(f"--painted {self.painted}: its folder does not exist")
        self.refine.check()


class Keys:
    """The lines typed on `stream` (stdin), read by a daemon thread so that the loop can watch files meanwhile."""

    def __init__(self, stream: Iterable[str] | None) -> None:
        self.lines: queue.Queue[str] = queue.Queue()
        if stream is not None:
            threading.Thread(target=self._read, args=(stream,), daemon=True).start()

    def _read(self, stream: Iterable[str]) -> None:
        try:
            for line in stream:
                self.lines.put(line.strip().lower())
        except (OSError, ValueError):  # stdin closed or not readable: no keys
            pass

    def skip(self) -> bool:
        """Whether an `s` line was typed since the last look (other lines are dropped)."""
        typed = False
        while not self.lines.empty():
            typed |= self.lines.get_nowait() == "s"
        return typed


def loop(
    workspace_root: Path, settings: LoopSettings | None = None, progress: bool = True, keys: Iterable[str] | None = None
) -> list[Path]:
    """Run `settings.rounds` rounds on the workspace (see the module doc); returns the avatar written by each.
    keys: the typed lines (stdin) where `s` skips a round's painting."""
    settings = settings or LoopSettings()
    settings.check()
    open_workspace(workspace_root)  # a one-line refusal before any work
    console = Console(stderr=True)
    typed = Keys(keys)
    avatars: list[Path] = []
    try:
        for number in range(1, settings.rounds + 1):
            console.rule(f"round {number} of {settings.rounds}: avatar {open_workspace(workspace_root).iteration:03d}")
            folder = suggest(workspace_root, settings.suggest, progress, hint=False)
            picture = visibility_path(open_workspace(workspace_root)).with_suffix(".png")
            console.print(f"where the video saw the avatar little: {picture}")
            register_painting(workspace_root, folder, settings, typed, console, progress)
            avatars.append(refine(workspace_root, settings.refine, progress))
            console.print(f"round {number} of {settings.rounds} done: avatar {avatars[-1]}")
    except KeyboardInterrupt:
        console.print(f"loop stopped after {len(avatars)} of {settings.rounds} rounds; what its finished stages wrote is kept")
        raise
    again = f"'avatarperfect loop {workspace_root}' again"
    console.print(f"next: avatarperfect evaluate {workspace_root} --test HELD_OUT/, or {again}", highlight=False)
    return avatars


def register_painting(
    workspace_root: Path, folder: Path, settings: LoopSettings, keys: Keys, console: Console, progress: bool
) -> None:
    """Wait for the painting and register it; a painting apply-edit refuses (wrong size, ...) is reported and
    the wait goes on for the next save. Returns once an edit is registered, the painting is the suggestion
    unchanged, or the person typed `s`."""
    suggested = folder / SUGGESTED
    target = settings.painted or f"a copy of {SUGGESTED} in {folder}/ (any name, PNG)"
    console.print(f"next: paint {suggested} (guide.png shows where to look) and save {target}; type s and Enter to skip")
    editor = _start_editor(settings.editor, suggested, console)
    while (painted := wait_for_painting(workspace_root, folder, settings, keys, console, editor)) is not None:
        try:
            apply_edit(workspace_root, painted, progress=progress, hint=False)
            return
        except UnchangedImage:
            console.print(f"{painted.name} is the suggestion unchanged: refining without a new edit")
            return
        except AvatarPerfectError as error:
            console.print(f"cannot register it: {error}; save it again, or type s and Enter to skip", highlight=False)


def wait_for_painting(
    workspace_root: Path, folder: Path, settings: LoopSettings, keys: Keys, console: Console, editor: subprocess.Popen | None
) -> Path | None:
    """The painted file once it is saved whole (see the module doc), or None when the person typed `s`."""
    suggested = folder / SUGGESTED
    original = suggested.read_bytes()
    started = _signatures(folder, settings.painted)
    stable: dict[Path, tuple[Signature, float]] = {}  # a changed file: its signature and since when it holds
    refused: dict[Path, Signature] = {}  # files read and refused as they are now: wait for another save
    with console.status(f"waiting for your painting (s and Enter: skip) in {settings.painted or folder}"):
        while True:
            if keys.skip():
                console.print("skipped: refining without a new edit")
                return None
            now = time.monotonic()
            for path, signature in _signatures(folder, settings.painted).items():
                if signature == started.get(path) or refused.get(path) == signature:
                    continue
                if stable.get(path, (None, 0.0))[0] != signature:
                    stable[path] = (signature, now)
                elif now - stable[path][1] >= settings.settle_s:
                    if not whole_image(path):
                        console.print(f"{path} is not a whole image yet; waiting for the save to finish")
                        refused[path] = signature
                    elif path == suggested:
                        return _move_painting_aside(workspace_root, folder, original, console)
                    else:
                        console.print(f"read {path}")
                        return path
            if editor is not None and editor.poll() not in (None, 0):
                console.print(f"the editor '{settings.editor}' exited with status {editor.returncode}")
                editor = None
            time.sleep(settings.poll_s)


def _signatures(folder: Path, painted: Path | None) -> dict[Path, Signature]:
    """(size, mtime) of each file that can be the painting: `painted`, or the images in `folder` (not hidden, not
    suggest's own but for suggested.png, which a person may paint over)."""
    if painted is not None:
        paths = [Path(painted), folder / SUGGESTED]
    else:
        paths = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")]
        paths = [p for p in paths if p.name not in SUGGESTION_FILES or p.name == SUGGESTED]
    signatures = {}
    for path in paths:
        try:
            stat = path.stat()
        except OSError:  # gone between the listing and the look, or not there yet
            continue
        signatures[path] = (stat.st_size, stat.st_mtime_ns)
    return signatures


def _start_editor(editor: str | None, image: Path, console: Console) -> subprocess.Popen | None:
    """Start the editor on `image` detached from the terminal, so that a Ctrl-C of the loop does not close it."""
    if editor is None:
        return None
    console.print(f"opening it with {editor}", highlight=False)
    try:
        return subprocess.Popen(
            [*shlex.split(editor), str(image)], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL, start_new_session=True,
        )  # fmt: skip
    except OSError as error:
        raise AvatarPerfectError(f"--editor '{editor}': cannot start it ({error.strerror or error})") from None


def _move_painting_aside(workspace_root: Path, folder: Path, original: bytes, console: Console) -> Path:
    """The person saved over suggested.png: its new content becomes painted.png (painted-2.png, ... if taken) and
    suggested.png gets its original bytes back, in one step under the workspace's lock."""
    painted = folder / "painted.png"
    number = 1
    while painted.exists():
        number += 1
        painted = folder / f"painted-{number}.png"
    with locked_workspace(workspace_root):
        content = (folder / SUGGESTED).read_bytes()
        with updated_folder(folder) as staging:
            atomic_write_bytes(staging / painted.name, content)
            atomic_write_bytes(staging / SUGGESTED, original)
    console.print(f"you saved over {SUGGESTED}: kept your painting as {painted} and put the original back")
    return painted
