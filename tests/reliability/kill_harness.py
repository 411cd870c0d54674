"""The kill harness: each workspace-writing stage, run as a real `python -m avatarperfect_cli` process on a private
copy of a prepared workspace, killed with SIGINT, SIGTERM or SIGKILL at a seeded random moment, then checked.

A stage is one `Stage` entry in STAGES: its name, `prepare(ws, inputs) -> argv`, and the stage whose finished
workspace it starts from (`base`). A future stage joins by adding its entry.

Each stage's reference is an uninterrupted run of it, in-process, on its own copy of the base: it is the new
state and times the kills. What a kill must leave (`Harness.check`):
- exit status 130 after SIGINT or SIGTERM, or 0 if the stage finished first (two more are accepted: see
  `_interrupt_status`); SIGKILL: any status;
- a readable manifest whenever a workspace is at the path (for `train-initial --force`: always one);
- after the next command (`apply-edit WS --list`, which takes the lock and cleans up): nothing hidden in or
  beside the workspace (staging folders, temporaries, the lock file), no avatar/NNN.ply the manifest does not
  commit, and the workspace either byte-identical to before ("old") or completely the new state ("new": the
  reference's files, the ones the reference left alone byte-identical, the manifest loading, every committed
  avatar loading, the current one rendering with `render --pose`, every registered edit complete).
  A stage that first brings derived data up to date in a commit of its own (refine refreshes the visibility
  record) may also leave the old state with that folder refreshed (`Stage.refreshes`); it counts as old.
  A command that runs several stages one after another (loop) may also leave the workspace after some of them
  (`Stage.steps`): "partial".
Anything else is "lost".

Kill moments, one phase drawn per kill:
- "startup": uniform over the time the process usually takes to reach the lock (imports; no stage running);
- "run": once the lock file appears, uniform over 1.2x the reference's duration (work, saves, or just after);
- "save": once the lock file appears, inside a randomly chosen save: each new hidden temporary or staging entry
  is the chosen one with probability 1/2, and the kill lands uniformly inside the SAVE_DELAY seconds that the
  test hook (io/atomic.py, $AVATARPERFECT_TEST_SAVE_DELAY) sleeps before the save's final rename.
"""

from __future__ import annotations

import hashlib
import json
import os
import random
import shutil
import signal
import statistics
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import torch
from typer.testing import CliRunner

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.cli import app
from avatarperfect_cli.io import read_image, write_image, write_pose
from avatarperfect_cli.io.atomic import SAVE_DELAY_VARIABLE
from avatarperfect_cli.io.workspace import lock_path, open_workspace
from avatarperfect_cli.stages.report import REPORT_FILES
from avatarperfect_cli.stages.workspace_data import EDITS, latest_suggestion, reference_pose

SAMPLE = Path(__file__).resolve().parents[2] / "examples" / "sample"
TRAIN_ARGS = ["--iterations", "10", "--resolution", "64", "--frames", "0:59:12"]
FAST_SUGGEST = ["--starts", "1", "--steps", "3", "--resolution", "32"]
SAVE_DELAY = 0.25  # seconds the test hook sleeps before each final rename
SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGKILL)
PHASES = {"startup": 1, "run": 5, "save": 4}  # relative weights
POLL_S = 0.005
CALIBRATE_FROM = 5  # kills per stage from which an uninterrupted process run times them
IGNORED_AFTER_S = 1.0  # a process that exits 0 this long after an early signal ignored it
EDIT_FILES = {"target.png", "mask.png", "background.png", "pose.json", "edit.json"}  # and edited.<suffix>
WS = "ws"  # the workspace's name inside its private folder ("box"), which holds nothing else


def invoke(*args: object, input: str | None = None):
    """The CLI in-process (typer's CliRunner), reading `input` on stdin."""
    return CliRunner().invoke(app, [str(a) for a in args], input=input)


def snapshot(root: Path) -> dict[str, str]:
    """Relative path -> sha256 of every file under `root` (empty when `root` is missing)."""
    if not root.is_dir():
        return {}
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*")) if p.is_file()}


def hidden_entries(root: Path) -> list[str]:
    """Paths under `root` whose name starts with a dot (what killed writers leave: staging, temporaries, locks).
    Safe while a running stage creates and deletes them (os.walk skips what vanished)."""
    found = []
    for folder, folders, files in os.walk(root):
        found += [os.path.relpath(os.path.join(folder, name), root) for name in folders + files if name.startswith(".")]
    return sorted(found)


# ------------------------------------------------------------------------------------------------ the stages


@dataclass(frozen=True)
class Stage:
    """name: unique label; prepare(ws, inputs) writes any input files under `inputs` and returns the command line
    (after `avatarperfect`) that runs the stage on workspace `ws`; base: the stage whose finished workspace this
    one starts from (None: no workspace yet); expected: the stage whose finished workspace is this one's new
    state (None: its own reference run; then the files that run left alone must stay byte-identical);
    refreshes: folders of derived data (e.g. "visibility") that the stage brings up to date, each in a commit of
    its own, before its result: the old workspace with any of them holding the reference's files (names; the
    contents free) also counts as old;
    outputs: the files the stage writes outside the workspace (relative to `inputs`): after a kill each is absent
    or complete, and only SIGKILL may leave a hidden temporary beside them; steps: the folders a command running
    several stages (loop) completes one after another before its result: a kill may leave each as before or with
    the reference's files (contents free: they hold timings) and the rest as before ("partial"); stdin: what the
    process reads on its standard input (None: nothing)."""

    name: str
    prepare: Callable[[Path, Path], list[str]]
    base: str | None = None
    expected: str | None = None
    refreshes: tuple[str, ...] = ()
    outputs: tuple[str, ...] = ()
    steps: tuple[str, ...] = ()
    stdin: str | None = None


def _train(*extra: str) -> Callable[[Path, Path], list[str]]:
    return lambda ws, inputs: ["train-initial", str(SAMPLE / "train"), str(ws), *TRAIN_ARGS, *extra]


def _painted_square(ws: Path, inputs: Path) -> list[str]:
    """Paint a white square over the middle of the latest suggestion (the background tool)."""
    suggested = read_image(latest_suggestion(open_workspace(ws)) / "suggested.png", "RGB")
    height, width = suggested.shape[:2]
    suggested[height * 3 // 8 : height * 5 // 8, width * 3 // 8 : width * 5 // 8] = 1.0
    write_image(inputs / "edited.png", suggested)
    return ["apply-edit", str(ws), str(inputs / "edited.png")]


def _region(ws: Path, inputs: Path) -> Path:
    """A selection mask over the middle of the latest suggestion."""
    height, width = read_image(latest_suggestion(open_workspace(ws)) / "suggested.png", "RGB").shape[:2]
    region = torch.zeros(height, width, 1)
    region[height // 4 : height * 3 // 4, width // 3 : width * 2 // 3] = 1.0
    write_image(inputs / "region.png", region)
    return inputs / "region.png"


STAGES: list[Stage] = [
    Stage("train-initial", _train()),
    Stage("visibility", lambda ws, inputs: ["visibility", str(ws)], base="train-initial"),
    Stage("suggest", lambda ws, inputs: ["suggest", str(ws), *FAST_SUGGEST], base="visibility"),
    Stage("simulate-user", lambda ws, inputs: ["simulate-user", str(ws), "--subject", str(SAMPLE)], base="suggest"),
    Stage("apply-edit", _painted_square, base="suggest"),
    Stage("apply-edit --fill", lambda ws, inputs: ["apply-edit", str(ws), "--region", str(_region(ws, inputs)), "--fill", "white"], base="suggest"),
    Stage("apply-edit --erase", lambda ws, inputs: ["apply-edit", str(ws), "--region", str(_region(ws, inputs)), "--erase", "center"], base="suggest"),
    Stage("apply-edit --remove", lambda ws, inputs: ["apply-edit", str(ws), "--remove", "1"], base="apply-edit"),
    Stage("refine", lambda ws, inputs: ["refine", str(ws), "--iterations", "5"], base="apply-edit", refreshes=("visibility",)),
    Stage("refine --revert-to", lambda ws, inputs: ["refine", str(ws), "--revert-to", "0"], base="refine"),
    Stage("evaluate", lambda ws, inputs: ["evaluate", str(ws), "--test", str(SAMPLE / "test"), "--frames", "0:19:10"], base="refine"),
    Stage(
        "simulate-user -o", lambda ws, inputs: ["simulate-user", str(ws), "--subject", str(SAMPLE), "-o", str(inputs / "painted.png")],
        base="suggest", outputs=("painted.png", "painted.json"),
    ),  # fmt: skip
    Stage(
        "report", lambda ws, inputs: ["report", str(ws), "--test", str(SAMPLE / "test"), "-o", str(inputs / "report")],
        base="refine", refreshes=("eval/000", "eval/001"), outputs=tuple(f"report/{name}" for name in REPORT_FILES),
    ),  # fmt: skip
    Stage("train-initial --force", _train("--force"), base="refine", expected="train-initial"),
    Stage("relink", lambda ws, inputs: ["relink", str(ws), str(SAMPLE / "train")], base="train-initial"),
    Stage(
        "loop", lambda ws, inputs: ["loop", str(ws), "--rounds", "1", "--iterations", "5", *FAST_SUGGEST],
        base="train-initial", steps=("visibility", "suggestions"), stdin="s\n",
    ),  # fmt: skip
]
STAGES_BY_NAME = {stage.name: stage for stage in STAGES}


# --------------------------------------------------------------------------------------------- the outcomes


@dataclass
class Outcome:
    """One kill: the signal, the phase and the moment (seconds after the start; None: the stage finished before
    its chosen moment), whether the lock file had appeared by then, the exit status, the state left ("old",
    "new" or "lost"), when the process ended (seconds after the start) and what was wrong."""

    stage: str
    signal: str
    phase: str
    moment: float | None
    lock_seen: bool
    exit_status: int
    state: str
    ended: float = 0.0
    problems: list[str] = field(default_factory=list)
    traceback: bool = False
    stderr_tail: str = ""


def summarise(outcomes: list[Outcome]) -> dict:
    """Counts per signal: kills, states, exit statuses, and the problems found."""
    summary: dict = {"kills": len(outcomes), "by_signal": {}, "problems": []}
    for name in ("SIGINT", "SIGTERM", "SIGKILL"):
        chosen = [o for o in outcomes if o.signal == name]
        summary["by_signal"][name] = {
            "kills": len(chosen),
            "states": dict(Counter(o.state for o in chosen)),
            "exit_statuses": {str(k): v for k, v in sorted(Counter(o.exit_status for o in chosen).items())},
            "phases": dict(Counter(o.phase for o in chosen)),
        }
    summary["interrupted_after_commit"] = sum(o.exit_status == 130 and o.state == "new" for o in outcomes)
    summary["tracebacks"] = sum(o.traceback for o in outcomes)
    summary["problems"] = [asdict(o) for o in outcomes if o.problems]
    return summary


def markdown_table(results: dict[str, dict]) -> str:
    """The counts of `summarise` per stage as a markdown table (for docs/reliability.md)."""
    lines = [
        "| stage | signal | kills | in a save | old state | after some steps | new state | lost | exit statuses |",
        "|---|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for stage, summary in results.items():
        if "by_signal" not in summary:
            continue
        for name, counts in summary["by_signal"].items():
            states = counts["states"]
            statuses = ", ".join(f"{status}: {count}" for status, count in counts["exit_statuses"].items())
            lines.append(
                f"| {stage} | {name} | {counts['kills']} | {counts['phases'].get('save', 0)} | {states.get('old', 0)} | {states.get('partial', 0)} | {states.get('new', 0)} "
                f"| {states.get('lost', 0)} | {statuses} |"
            )
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------ the harness


@dataclass
class Reference:
    """A stage's uninterrupted run: its finished workspace, the files before and after, its duration."""

    workspace: Path
    before: dict[str, str]
    after: dict[str, str]
    seconds: float


@dataclass
class Watch:
    """What the harness saw of one process, in seconds after its start: when the lock file appeared, when the
    signal was sent (None: never), when it ended, and the hidden temporaries and staging folders (saves)."""

    lock_at: float | None = None
    moment: float | None = None
    ended: float = 0.0
    saves: set[str] = field(default_factory=set)


@dataclass
class Timing:
    """How an uninterrupted run of a stage as a process goes: seconds from the lock file appearing to the exit,
    and the saves it made (hidden temporaries and staging folders seen)."""

    seconds: float
    saves: int


@contextmanager
def save_delay(seconds: float) -> Iterator[None]:
    """Set the test hook's delay for in-process runs."""
    previous = os.environ.get(SAVE_DELAY_VARIABLE)
    os.environ[SAVE_DELAY_VARIABLE] = str(seconds)
    try:
        yield
    finally:
        if previous is None:
            del os.environ[SAVE_DELAY_VARIABLE]
        else:
            os.environ[SAVE_DELAY_VARIABLE] = previous


class Harness:
    """Runs and checks kills under `root`; builds each stage's reference once, in-process, when first needed."""

    def __init__(self, root: Path, stages: list[Stage] = STAGES) -> None:
        self.root = root
        self.stages = {stage.name: stage for stage in stages}
        self.references: dict[str, Reference] = {}
        self.rendered: set[str] = set()  # avatar hashes already rendered by `render --pose`
        self.startup_seconds: list[float] = []  # time from the start to the lock file, per run
        self.timings: dict[str, Timing] = {}

    def reference(self, name: str) -> Reference:
        if name not in self.references:
            stage = self.stages[name]
            box, inputs = self._fresh(self.root / "references" / name, stage)
            workspace = box / WS
            argv = stage.prepare(workspace, inputs)
            before = snapshot(workspace)
            start = time.perf_counter()
            with save_delay(SAVE_DELAY):
                result = invoke(*argv, input=stage.stdin)
            seconds = time.perf_counter() - start
            assert result.exit_code == 0, f"reference run of {name} failed: {result.output}"
            assert invoke("apply-edit", workspace, "--list").exit_code == 0
            self.references[name] = Reference(workspace, before, snapshot(workspace), seconds)
        return self.references[name]

    def _fresh(self, folder: Path, stage: Stage) -> tuple[Path, Path]:
        """A new private `folder` with box/ (holding a copy of the base workspace, if any) and inputs/."""
        shutil.rmtree(folder, ignore_errors=True)
        box, inputs = folder / "box", folder / "inputs"
        box.mkdir(parents=True)
        inputs.mkdir()
        if stage.base is not None:
            shutil.copytree(self.reference(stage.base).workspace, box / WS)
        return box, inputs

    def kill_stage(self, name: str, kills: int, seed: int) -> list[Outcome]:
        """`kills` kills of stage `name`: signals in turn (starting at the stage's position in STAGES, so one
        kill per stage still spreads the three signals), phases and moments drawn from `seed`. From
        CALIBRATE_FROM kills on, one uninterrupted run as a process first times the kills (`Timing`); below,
        the in-process reference does (a process takes longer: it loads numba's cache, torch's lazy parts)."""
        stage = self.stages[name]
        self.reference(stage.expected or name)
        if kills >= CALIBRATE_FROM and name not in self.timings:
            self.timings[name] = self.calibrate(stage)
        rng = random.Random(f"{seed}/{name}")
        offset = list(self.stages).index(name)
        outcomes = []
        for index in range(kills):
            signum = SIGNALS[(index + offset) % len(SIGNALS)]
            phase = rng.choices(list(PHASES), weights=list(PHASES.values()))[0]
            outcomes.append(self.kill_once(stage, signum, phase, rng, self.root / "kills" / f"{name}-{index:03d}"))
            shutil.rmtree(self.root / "kills" / f"{name}-{index:03d}", ignore_errors=True)
        return outcomes

    def calibrate(self, stage: Stage) -> Timing:
        """One uninterrupted run of `stage` as a process, checked like a kill (it must end in the new state)."""
        folder = self.root / "kills" / f"{stage.name}-timing"
        process, workspace, before = self._start(stage, folder)
        watch = self._watch(process, workspace, None, "finish", random.Random(0), Timing(0.0, 0))
        outcome = self._finish(stage, process, signal.SIGINT, "finish", watch, workspace, before, folder)
        assert outcome.state == "new" and not outcome.problems, f"uninterrupted run of {stage.name}: {outcome}"
        shutil.rmtree(folder, ignore_errors=True)
        locked = watch.ended - watch.lock_at if watch.lock_at is not None else POLL_S  # a lock held < one poll
        return Timing(locked, len(watch.saves))

    def kill_once(self, stage: Stage, signum: int, phase: str, rng: random.Random, folder: Path) -> Outcome:
        process, workspace, before = self._start(stage, folder)
        reference = self.reference(stage.expected or stage.name)
        timing = self.timings.get(stage.name, Timing(reference.seconds, 0))
        watch = self._watch(process, workspace, signum, phase, rng, timing)
        return self._finish(stage, process, signum, phase, watch, workspace, before, folder)

    def _start(self, stage: Stage, folder: Path) -> tuple[subprocess.Popen, Path, dict[str, str]]:
        """The stage as a process on a fresh copy of its base: (process, workspace, the files before)."""
        box, inputs = self._fresh(folder, stage)
        workspace = box / WS
        argv = stage.prepare(workspace, inputs)
        before = snapshot(workspace)
        with open(folder / "stderr.txt", "wb") as err:
            process = subprocess.Popen(
                [sys.executable, "-m", "avatarperfect_cli", *argv], stdout=subprocess.DEVNULL, stderr=err,
                stdin=subprocess.DEVNULL if stage.stdin is None else subprocess.PIPE,
                env={**os.environ, SAVE_DELAY_VARIABLE: str(SAVE_DELAY)}, preexec_fn=default_sigint,
            )  # fmt: skip
        if process.stdin is not None:
            process.stdin.write(stage.stdin.encode())
            process.stdin.close()
        return process, workspace, before

    def _finish(
        self, stage: Stage, process: subprocess.Popen, signum: int, phase: str, watch: Watch, workspace: Path,
        before: dict[str, str], folder: Path,
    ) -> Outcome:  # fmt: skip
        status = process.wait(timeout=600)
        lock_seen = watch.lock_at is not None and (watch.moment is None or watch.lock_at <= watch.moment)
        outcome = Outcome(stage.name, signal.Signals(signum).name, phase, watch.moment, lock_seen, status, "lost")
        outcome.ended = watch.ended
        text = (folder / "stderr.txt").read_text(errors="replace")
        outcome.traceback, outcome.stderr_tail = "Traceback" in text, text[-600:]
        self.check(stage, outcome, workspace, before, folder)
        return outcome

    def _watch(
        self, process: subprocess.Popen, workspace: Path, signum: int | None, phase: str, rng: random.Random, timing: Timing
    ) -> Watch:
        """Follow the process (lock file, saves), send `signum` at the phase's moment, wait for its end."""
        watch = Watch()
        start = time.perf_counter()
        lock = lock_path(workspace)
        usual_startup = statistics.median(self.startup_seconds) if self.startup_seconds else 2.0
        deadline = start + rng.uniform(0.0, usual_startup) if phase == "startup" else None
        chosen_save = rng.randint(1, timing.saves) if timing.saves else None  # else each save with probability 1/2
        while process.poll() is None:
            now = time.perf_counter()
            if watch.lock_at is None and lock.exists():
                watch.lock_at = now - start
                self.startup_seconds.append(watch.lock_at)
                if phase == "run":
                    deadline = now + rng.uniform(0.0, 1.2 * timing.seconds)
            if watch.lock_at is not None and (phase in ("save", "finish")) and deadline is None:
                for entry in hidden_entries(workspace.parent):
                    if entry not in watch.saves and ".tmp" in entry:
                        watch.saves.add(entry)
                        chosen = len(watch.saves) == chosen_save if chosen_save else rng.random() < 0.5
                        if phase == "save" and chosen:
                            deadline = now + rng.uniform(0.0, SAVE_DELAY)
                            break
            if signum is not None and deadline is not None and now >= deadline and watch.moment is None:
                process.send_signal(signum)
                watch.moment = now - start
            time.sleep(POLL_S)
        watch.ended = time.perf_counter() - start
        return watch

    def check(self, stage: Stage, outcome: Outcome, workspace: Path, before: dict[str, str], folder: Path) -> None:
        """Fill in `outcome.state` and `outcome.problems` (see the module doc)."""
        problems = outcome.problems
        status = outcome.exit_status
        if outcome.lock_seen and outcome.traceback:
            problems.append("a traceback on stderr")
        if workspace.exists() or stage.base is not None:
            try:
                open_workspace(workspace)
            except Exception as error:  # noqa: BLE001 - any failure to read is the finding
                problems.append(f"right after the kill the manifest does not load: {error}")
        after_next = invoke("apply-edit", workspace, "--list")
        if after_next.exit_code != 0 and not (stage.base is None and not workspace.exists()):
            problems.append(f"the next command failed: {after_next.output.strip()[-300:]}")
        leftovers = sorted(entry.name for entry in workspace.parent.iterdir() if entry.name != WS) + hidden_entries(workspace)
        if leftovers:
            problems.append(f"left after the next command: {leftovers}")
        now = snapshot(workspace)
        reference = self.reference(stage.expected or stage.name)
        written = bool(stage.outputs) and all(_complete(folder / "inputs" / name) for name in stage.outputs)
        if now == before and reference.after == reference.before and (status == 0 or written):
            outcome.state = "new"  # a stage whose result is its outputs alone (checked below) finished
        elif now == before or _old_but_refreshed(stage, now, before, reference.after):
            # a run that ended well and recomputed its refreshed folders (their last bits follow the threads'
            # timing when the cores are shared) left the new state, and so did one the signal ended after it had
            # written all its outputs whole (the interpreter exiting); a run killed before, the old state refreshed
            finished = now != before and (written or (status == 0 and not stage.outputs))
            outcome.state = "new" if finished else "old"
        elif _after_some_steps(stage, now, before, reference.after):
            damage = self.check_workspace(workspace, folder)
            problems.extend(damage)
            outcome.state = "lost" if damage else "partial"
        elif self._is_new_state(stage, now, before, reference, problems):
            damage = self.check_workspace(workspace, folder)
            problems.extend(damage)
            outcome.state = "lost" if damage else "new"
        else:
            problems.append(f"neither the old nor the new state: {_difference(now, before, reference.after)}")
        if status == 0 and outcome.state != "new":
            problems.append("exit status 0 but the stage's result is missing")
        if status == 0 and outcome.moment is not None and outcome.ended - outcome.moment > IGNORED_AFTER_S and not outcome.lock_seen:
            problems.append(f"{outcome.signal} before the stage started was ignored: it ran to the end")
        if outcome.signal != "SIGKILL" and not _interrupt_status(outcome):
            problems.append(f"exit status {status} after {outcome.signal}")
        problems.extend(_output_problems(stage, folder / "inputs", outcome))

    def _is_new_state(self, stage: Stage, now: dict[str, str], before: dict[str, str], reference: Reference, problems: list[str]) -> bool:
        if set(now) != set(reference.after):
            return False
        if stage.expected is None:
            untouched = [path for path, digest in reference.before.items() if reference.after.get(path) == digest]
            changed = [path for path in untouched if now.get(path) != before.get(path)]
            if changed:
                problems.append(f"files the stage leaves alone changed: {changed}")
                return False
        return True

    def check_workspace(self, workspace: Path, scratch: Path) -> list[str]:
        """Problems of a workspace in its new state: manifest, committed avatars, a render of the current one, edits."""
        try:
            ws = open_workspace(workspace)
            for iteration in sorted(ws.committed_avatars()):
                Avatar.load(ws.avatar_path(iteration))
        except Exception as error:  # noqa: BLE001
            return [f"does not load: {error}"]
        problems = []
        current = hashlib.sha256(ws.avatar_path().read_bytes()).hexdigest()
        if current not in self.rendered:
            pose = scratch / "check-pose.json"
            write_pose(pose, reference_pose(ws))
            result = invoke("render", workspace, "--pose", pose, "-o", scratch / "check.png")
            if result.exit_code != 0 or not (scratch / "check.png").is_file():
                problems.append(f"render --pose failed: {result.output.strip()[-300:]} {result.exception!r}")
            else:
                self.rendered.add(current)
        for folder in ws.numbered_folders(EDITS):
            names = {p.name for p in folder.iterdir()}
            if not EDIT_FILES <= names or not any(name.startswith("edited.") for name in names):
                problems.append(f"edit {folder.name} is incomplete: {sorted(names)}")
        for path in (workspace / "avatar").glob("*.ply"):
            if not path.stem.isdigit() or int(path.stem) not in ws.committed_avatars():
                problems.append(f"{path.name} is not committed")
        return problems


def _output_problems(stage: Stage, inputs: Path, outcome: Outcome) -> list[str]:
    """What is wrong with the stage's outputs outside the workspace after a kill (see `Stage.outputs`)."""
    problems = []
    for name in stage.outputs:
        path = inputs / name
        if outcome.exit_status == 0 and not path.is_file():
            problems.append(f"exit status 0 but {name} is missing")
        if path.is_file() and not _complete(path):
            problems.append(f"{name} is incomplete")
        hidden = sorted(p.name for p in path.parent.glob(f".{path.stem}.tmp-*")) if path.parent.is_dir() else []
        if hidden and outcome.signal != "SIGKILL":
            problems.append(f"left beside the outputs: {hidden}")
    return problems


def _complete(path: Path) -> bool:
    """Whether an output file reads back whole: an image, a video with a frame, a JSON object."""
    try:
        if path.suffix == ".png":
            read_image(path)
        elif path.suffix == ".json":
            json.loads(path.read_text())
        else:
            capture = cv2.VideoCapture(str(path))
            readable = capture.read()[0]
            capture.release()
            return readable
    except Exception:  # noqa: BLE001 - any failure to read is the finding
        return False
    return True


def _old_but_refreshed(stage: Stage, now: dict[str, str], before: dict[str, str], expected: dict[str, str]) -> bool:
    """Whether `now` is the old state but for some of the stage's refreshed folders, each as before or holding the
    reference's file names (their contents are a recomputation, whose last bits follow the threads' timing when
    the cores are shared)."""
    if not stage.refreshes or now == expected:  # a stage whose result is its refreshed folders finished
        return False

    def part(files: dict[str, str], folder: str | None) -> dict[str, str]:
        """The files inside `folder` (None: outside every refreshed folder) with their hashes."""
        return {path: digest for path, digest in files.items() if _folder_of(path, stage.refreshes) == folder}

    if part(now, None) != part(before, None):
        return False
    return all(
        part(now, folder) == part(before, folder) or set(part(now, folder)) == set(part(expected, folder))
        for folder in stage.refreshes
    )


def _folder_of(path: str, folders: tuple[str, ...]) -> str | None:
    """The one of `folders` that holds `path`, or None."""
    return next((folder for folder in folders if Path(path).is_relative_to(folder)), None)


def _after_some_steps(stage: Stage, now: dict[str, str], before: dict[str, str], expected: dict[str, str]) -> bool:
    """Whether `now` is the old state but for some of the stage's step folders, each holding the reference's file names."""
    if not stage.steps:
        return False

    def names(files: dict[str, str], folder: str | None) -> set[str]:
        return {path for path in files if _folder_of(path, stage.steps) == folder}

    outside = {path: digest for path, digest in now.items() if path in names(now, None)}
    if outside != {path: digest for path, digest in before.items() if path in names(before, None)}:
        return False
    return all(names(now, folder) in (names(before, folder), names(expected, folder)) for folder in stage.steps)


def _difference(now: dict[str, str], before: dict[str, str], expected: dict[str, str]) -> str:
    return (
        f"missing vs before {sorted(set(before) - set(now))}, extra vs before {sorted(set(now) - set(before))}, "
        f"missing vs new {sorted(set(expected) - set(now))}, extra vs new {sorted(set(now) - set(expected))}"
    )


def _interrupt_status(outcome: Outcome) -> bool:
    """Whether a SIGINT or SIGTERM ended the process as promised: 130 (0 if the stage finished first). Three more
    are accepted, all outside the stage: death by the signal itself before the lock was taken (the interpreter
    was starting, before the CLI's handlers) or with the stage's work complete (the interpreter was exiting and
    had restored the default handlers), and death by SIGINT after "interrupted" was printed: under `python -m`,
    CPython ends itself by SIGINT when a KeyboardInterrupt once passed through exec() of a string, even if it was
    handled (the `avatarperfect` script exits 130 there; a shell shows 130 for both)."""
    status, signum = outcome.exit_status, signal.Signals[outcome.signal]
    if status in (0, 130):
        return True
    if status == -signum and (not outcome.lock_seen or outcome.state == "new"):
        return True
    return status == -signal.SIGINT and outcome.stderr_tail.rstrip().endswith("interrupted: nothing was changed")


def default_sigint() -> None:
    """In the child: Ctrl-C's default, even when the harness was started with SIGINT ignored (a background job)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def write_results(path: Path, stage: str, summary: dict) -> None:
    """Merge one stage's summary into the JSON results file at `path`."""
    results = json.loads(path.read_text()) if path.is_file() else {}
    results[stage] = summary
    path.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":  # python -m tests.reliability.kill_harness RESULTS.json: the counts as a markdown table
    print(markdown_table(json.loads(Path(sys.argv[1]).read_text())))
