"""Suggestion quality and speed on the synthetic sample (issue 7's measurements).

    python -m benchmarks.suggest WORKSPACE SAMPLE_DIR [--images docs/images] [--seeds 50]

WORKSPACE: a workspace trained on SAMPLE_DIR/train (e.g. `make demo`'s demo/ws after train-initial).
Prints tables of
  1. how much of what the video never showed each kind of view shows: the suggestion (body pose +
     camera), the canonical-pose camera-only suggestion, and the median of 20 random natural poses and
     cameras. Two counts on the subject's exact render at the view: pixels of unseen surface (template
     faces no pixel of any training frame shows: soles, the top of the head, armpits, ...) and pixels
     of the texture's hidden regions (inner arms, armpits, crotch: the study's PSNR-hidden regions);
  2. joint-limit and self-intersection checks of the suggestions of `--seeds` seeds;
  3. five successive suggestions, each registered as an edit view (a simulated user's painting) before
     the next, and a contact sheet of them;
  4. wall time of `avatarperfect visibility` and `suggest`, cold (empty numba cache) and warm (medians).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.datasets import load_people_snapshot
from avatarperfect_cli.io import read_image, read_pose, write_image
from avatarperfect_cli.io.workspace import open_workspace
from avatarperfect_cli.refinement.collision import BodyCapsules
from avatarperfect_cli.refinement.pose_prior import joint_limit_violations, load_pose_prior
from avatarperfect_cli.refinement.suggest import SuggestConfig, suggest_view
from avatarperfect_cli.sample.subject import SyntheticSubject
from avatarperfect_cli.sample.texture import HIDDEN_REGIONS, REGION
from avatarperfect_cli.stages.apply_edit import apply_edit
from avatarperfect_cli.stages.simulate_user import simulate_user
from avatarperfect_cli.stages.suggest import suggest
from avatarperfect_cli.stages.visibility import current_visibility
from avatarperfect_cli.stages.workspace_data import reference_pose

HIDDEN_LABELS = torch.tensor([REGION[name] for name in HIDDEN_REGIONS])


def hidden_pixels(subject: SyntheticSubject, pose) -> int:
    """Pixels of the subject's exact render at `pose` that show the hidden texture regions."""
    labels = torch.from_numpy(subject.render(pose.body_pose, pose.transl, pose.camera).labels)
    return int(torch.isin(labels, HIDDEN_LABELS).sum())


def unseen_pixels(subject: SyntheticSubject, unseen: np.ndarray, pose) -> int:
    """Pixels of the subject's exact render at `pose` that show faces flagged in `unseen` (F,) bool."""
    ids = subject.face_ids(pose.body_pose, pose.transl, pose.camera)
    return int(unseen[ids[ids >= 0]].sum())


def table(title: str, header: list[str], rows: list[list[str]]) -> None:
    widths = [max(len(str(cell)) for cell in column) for column in zip(header, *rows)]
    print(f"\n{title}")
    print(" | ".join(h.ljust(w) for h, w in zip(header, widths)))
    print("-+-".join("-" * w for w in widths))
    for row in rows:
        print(" | ".join(str(c).ljust(w) for c, w in zip(row, widths)))


def cli_seconds(*args: str, env: dict[str, str]) -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "avatarperfect_cli", *args], check=True, env=env, capture_output=True)
    return time.perf_counter() - start


def views_and_validity(args, shown, avatar, visibility, prior, capsules, reference) -> None:
    """Tables 1 and 2: what the suggested, camera-only and random views show; validity over the seeds."""

    def run(mode: str, seed: int):
        return suggest_view(avatar, visibility, prior, capsules, reference, SuggestConfig(body_pose=mode, seed=seed))

    validity = {"limit": 0, "intersect": 0}
    suggested_shown, seconds = [], []
    for seed in range(args.seeds):
        start = time.perf_counter()
        result = run("optimise", seed)
        seconds.append(time.perf_counter() - start)
        validity["limit"] += bool(joint_limit_violations(result.pose.body_pose))
        validity["intersect"] += bool(capsules.intersecting_pairs(result.pose.body_pose))
        if seed < args.shown_seeds:
            suggested_shown.append(shown(result.pose))
    canonical = [shown(run("canonical", seed).pose) for seed in range(args.shown_seeds)]
    randoms = [shown(run("random", seed).pose) for seed in range(args.randoms)]
    for column, title in ((0, "unseen surface (faces no training frame shows)"), (1, "hidden texture regions (inner arms, armpits, crotch)")):
        median_random = statistics.median(r[column] for r in randoms)
        rows = []
        for name, values in (("suggested (pose + camera)", suggested_shown), ("canonical pose, camera only", canonical)):
            median = statistics.median(v[column] for v in values)
            rows.append([name, f"{median:.0f}", f"{median / max(median_random, 1):.2f}x", " ".join(str(v[column]) for v in values)])
        rows.append([f"random natural pose + camera ({args.randoms})", f"{median_random:.0f}", "1.00x",
                     f"range {min(r[column] for r in randoms)}-{max(r[column] for r in randoms)}"])  # fmt: skip
        table(f"Pixels of {title} shown, seeds 0-{args.shown_seeds - 1}", ["view", "median px", "vs random", "per seed"], rows)
    table(
        f"Validity of {args.seeds} suggestions (seeds 0-{args.seeds - 1})",
        ["check", "violations"],
        [["joint limits", str(validity["limit"])], ["limb through body (capsules, > 1 cm)", str(validity["intersect"])],
         ["search time per suggestion, median (in-process)", f"{statistics.median(seconds):.2f} s"]],
    )  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("workspace", type=Path)
    parser.add_argument("sample", type=Path)
    parser.add_argument("--images", type=Path, default=Path("docs/images"))
    parser.add_argument("--seeds", type=int, default=50)
    parser.add_argument("--randoms", type=int, default=20)
    parser.add_argument("--shown-seeds", type=int, default=10, help="seeds whose views are counted (table 1)")
    parser.add_argument("--sequence-only", action="store_true", help="only tables 3 and 4 (the sequence, CLI times)")
    args = parser.parse_args()
    subject = SyntheticSubject.from_dataset(args.sample / "train")
    scratch = Path(tempfile.mkdtemp(prefix="suggest-bench-"))
    ws = scratch / "ws"
    shutil.copytree(args.workspace, ws, ignore=shutil.ignore_patterns("suggestions", "edits", "visibility", "eval"))
    workspace = open_workspace(ws)
    avatar = Avatar.load(workspace.require_avatar())
    reference = reference_pose(workspace)
    prior = load_pose_prior("builtin", reference.body_pose)
    capsules = BodyCapsules.from_points(avatar.params["means"].detach(), avatar.skin_weights.detach(), avatar.rest_joints)
    visibility = current_visibility(workspace, avatar, 0.01, progress=False).visibility

    train = load_people_snapshot(args.sample / "train", downscale=1)
    unseen = subject.unseen_faces(train.body_pose, train.transl, train.camera)

    def shown(pose) -> tuple[int, int]:
        """(unseen-surface pixels, hidden-texture pixels) of the subject's exact render at `pose`."""
        return unseen_pixels(subject, unseen, pose), hidden_pixels(subject, pose)

    if not args.sequence_only:
        views_and_validity(args, shown, avatar, visibility, prior, capsules, reference)

    # 3: five successive suggestions, each registered as an edit view before the next
    frames, rows = [], []
    painted = scratch / "painted.png"
    for round_index in range(5):
        folder = suggest(ws, progress=False)
        simulate_user(ws, args.sample, output=painted, progress=False, force=True)
        apply_edit(ws, painted, progress=False)
        pose = read_pose(folder / "pose.json")
        summary = json.loads((folder / "suggestion.json").read_text())
        rows.append([folder.name, f"{summary['azimuth_deg']:.0f}", f"{summary['elevation_deg']:.0f}",
                     f"{summary['objective']:.0f}", *map(str, shown(pose))])  # fmt: skip
        frames.append(torch.cat([read_image(folder / "suggested.png", "RGB"), read_image(folder / "guide.png", "RGB")], dim=0))
    table("Five successive suggestions (each registered as an edit before the next)",
          ["suggestion", "azimuth deg", "elevation deg", "objective", "unseen px", "hidden px"], rows)  # fmt: skip
    args.images.mkdir(parents=True, exist_ok=True)
    sheet = torch.cat(frames, dim=1)
    write_image(args.images / "suggest_sequence.png", torch.nn.functional.interpolate(
        sheet.permute(2, 0, 1)[None], scale_factor=0.5, mode="area")[0].permute(1, 2, 0))  # fmt: skip

    # 4: CLI wall times, cold (fresh numba cache) and warm
    env = dict(os.environ, NUMBA_CACHE_DIR=str(scratch / "numba-cache"))
    timing_ws = scratch / "timing"
    rows = []
    for stage, extra in (("visibility", []), ("suggest", [])):
        shutil.copytree(ws, timing_ws, dirs_exist_ok=False, ignore=shutil.ignore_patterns("visibility"))
        cold = cli_seconds(stage, str(timing_ws), *extra, env=env)
        warm = []
        for _ in range(3):
            shutil.rmtree(timing_ws / "visibility", ignore_errors=True)
            if stage == "suggest":
                current_visibility(open_workspace(timing_ws), avatar, 0.01, progress=False)
            warm.append(cli_seconds(stage, str(timing_ws), *extra, env=env))
        rows.append([stage, f"{cold:.1f}", f"{statistics.median(warm):.1f}", " ".join(f"{w:.1f}" for w in warm)])
        shutil.rmtree(timing_ws)
    table("Wall time of the CLI (s), 2 CPU cores; cold = empty numba cache", ["command", "cold", "warm median", "warm runs"], rows)
    shutil.rmtree(scratch, ignore_errors=True)
    print(f"\ncontact sheet of the five suggestions (suggested above guide): {args.images / 'suggest_sequence.png'}")

if __name__ == "__main__":
    main()
