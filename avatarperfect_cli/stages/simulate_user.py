"""The `simulate-user` stage: paint the latest suggestion as a careful person would, for synthetic subjects.

The subject's exact appearance in the suggested pose is rendered by the sample module, by default with its
joints where the avatar's skeleton puts them (a fitted skeleton is not the subject's: a person pictures the
subject in the pose the avatar shows, not a few pixels beside it); the simulated user
(`sample.simulated_user`) paints white over what should be background and the true colours (or
each blob's mean colour) over what is wrong, within a budget. The result is an ordinary edited PNG
for `apply-edit`, written as ws/suggestions/NNN/simulated_edit.png unless another path is given, with its
statistics beside it (simulated_edit.json). Another path must be a .png outside the workspace; it and its .json are
checked before any work and, unless `force`, must not exist yet.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

from rich.console import Console

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.io import atomic_write_text, read_image, read_pose, write_image
from avatarperfect_cli.errors import InputFileError
from avatarperfect_cli.io.atomic import updated_folder
from avatarperfect_cli.io.outputs import check_new_output
from avatarperfect_cli.io.workspace import locked_workspace
from avatarperfect_cli.sample.simulated_user import PaintResult, UserConfig, paint, pictured_truth
from avatarperfect_cli.sample.subject import SyntheticSubject
from avatarperfect_cli.stages.workspace_data import latest_suggestion, transl_offset

SIMULATED_EDIT = "simulated_edit.png"


def subject_folder(folder: Path) -> Path:
    """A make-sample folder given as SAMPLE/ (its train/ split is used) or as one of its splits."""
    folder = Path(folder)
    if not (folder / "subject.json").is_file() and (folder / "train" / "subject.json").is_file():
        return folder / "train"
    return folder


def simulate_user(
    workspace_root: Path, subject: Path | None = None, config: UserConfig | None = None,
    output: Path | None = None, progress: bool = True, force: bool = False,
) -> PaintResult:  # fmt: skip
    """Paint the workspace's latest suggestion; `subject` defaults to the workspace's own dataset."""
    config = config or UserConfig()
    if output is not None:
        check_painting_output(Path(output), Path(workspace_root), force)
    with locked_workspace(workspace_root) as workspace:
        folder = latest_suggestion(workspace)
        source = subject_folder(subject) if subject is not None else workspace.dataset()
        truth_model = SyntheticSubject.from_dataset(source)
        pose = read_pose(folder / "pose.json")
        suggested = read_image(folder / "suggested.png", "RGB")
        alpha = read_image(folder / "suggested_alpha.png", "L")[..., 0]
        rest_joints = Avatar.load(workspace.require_avatar()).rest_joints
        truth = pictured_truth(truth_model, pose, rest_joints, transl_offset(workspace), config.truth_pose)
        result = paint(suggested, alpha, truth, config)
        path = Path(output) if output is not None else folder / SIMULATED_EDIT
        if output is None:  # inside the workspace: the image and its stats appear together
            with updated_folder(folder) as staging:
                _write_painting(staging / SIMULATED_EDIT, result)
        else:
            _write_painting(path, result)
    stats = result.stats
    Console(stderr=True, quiet=not progress).print(
        f"painted {stats.painted_pixels:,} pixels ({100 * stats.budget_used:.0f}% of the budget) into {path}"
    )
    return result


def check_painting_output(output: Path, workspace_root: Path, force: bool) -> None:
    """Refuse, before any work, an output that is not a new .png outside the workspace (and its .json beside it)."""
    if output.resolve().is_relative_to(workspace_root.resolve()):
        raise InputFileError(output, f"is inside the workspace {workspace_root}; leave out -o to paint the suggestion's {SIMULATED_EDIT}")
    check_new_output(output, (".png",), force)
    check_new_output(output.with_suffix(".json"), (".json",), force)


def _write_painting(path: Path, result: PaintResult) -> None:
    """The painted image at `path` and its statistics beside it (.json)."""
    write_image(path, result.image)
    atomic_write_text(path.with_suffix(".json"), json.dumps(asdict(result.stats), indent=2) + "\n")
