"""The paper's user study (Table 2), reproduced with a simulated user on synthetic subjects.

    python -m benchmarks.study OUT_DIR [--presets default female tall] [--rounds 5] [--resolution 512]
                               [--conditions initial ap-exact ...] [--seeds 0 1 2] [--body fit|exact]
                               [--pose-noise DEG] [--max-gaussians N]

For each subject (a make-sample preset) and seed one initial avatar is trained (2000 iterations, that
seed), then every condition runs `--rounds` rounds on its own copy of it (round r of seed s draws its
suggestion and refine with seed s * rounds + r). One seed decides little: the same code on another
machine, or another thread count, moves one subject's five-round result by about 0.3 dB (numba's
parallel sums add in another order, and training amplifies it), so several seeds report the mean gain
and its spread. Layout: OUT_DIR/PRESET/sample, OUT_DIR/PRESET/seed-S/{initial-ws, CONDITION, ...}.
The avatar's body is fitted to the masks (`--body fit`, what a user gets) or the subject's own (`exact`,
the best case). With `--pose-noise DEG` the initial avatar trains on OUT_DIR/PRESET/sample/train-noisy,
the training video with its poses perturbed as a pose estimator's (`motions.with_estimation_noise`), and
with `train-initial --refine-poses`, as a user with estimated poses would; the simulated user and the
held-out truth keep the subject's exact body and poses, and scoring uses the workspace's own body and offset.
    initial        no edits
    video-only     each round refines on the video alone (no suggestion, no edit): what the edits add to refine
    ap-exact       AvatarPerfect: suggested body pose + camera, simulated user with the true colours, refine
    ap-paper-objective  ap-exact with the paper's suggestion objective (`suggest --exposure-poses 0`)
    ap-flat        the same with the flat-colour user (each blob its mean colour: the inpaint tool)
    ap-keep-shapes ap-exact with `refine --keep-shapes` (edit steps leave scales and rotations alone)
    random         random natural pose + camera, exact user, refine (is the suggestion worth it?)
    canonical      canonical pose, suggested camera only, exact user, refine (is the body pose worth it?)
    erase-center   SuperSplat: canonical pose, the worst of 12 orbit views, erase the Gaussians whose
                   centres fall where the simulated user paints background; no training
    erase-splat    the same with Erase Splat (visibility > 0.01 at a selected pixel)
Columns: held-out IoU, PSNR, SSIM (full frame on white, as the paper), PSNR on the subject's bounding
box, PSNR over the hidden texture regions (inner arms, armpits, crotch; each on its own in a second
table), PSNR over the surface the training video never showed (template faces no training frame's pixel
shows: soles, the top of the head, ...), training-frame PSNR change (worst round), Gaussians deleted, seconds per round (suggest + refine, not the user). Writes OUT_DIR/study.md
(the tables, as in docs/study.md), OUT_DIR/study.json and OUT_DIR/images/*.png (the first seed's).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import statistics
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.datasets import load_people_snapshot, write_people_snapshot
from avatarperfect_cli.io import PoseFile, read_image, write_image
from avatarperfect_cli.io.workspace import open_workspace
from avatarperfect_cli.refinement.suggest import SuggestConfig
from avatarperfect_cli.render.camera import rotation_about
from avatarperfect_cli.sample.generate import make_sample
from avatarperfect_cli.sample.motions import Motion, with_estimation_noise
from avatarperfect_cli.sample.simulated_user import TRUTH_POSES, UserConfig, paint, pictured_truth
from avatarperfect_cli.sample.subject import SyntheticSubject
from avatarperfect_cli.sample.texture import HIDDEN_REGIONS, REGION
from avatarperfect_cli.stages.apply_edit import apply_edit, erase_region
from avatarperfect_cli.stages.refine import RefineSettings, refine
from avatarperfect_cli.stages.simulate_user import simulate_user
from avatarperfect_cli.stages.suggest import SuggestSettings, suggest
from avatarperfect_cli.stages.train_initial import BodySettings, InitialFit, VideoSettings, train_initial
from avatarperfect_cli.stages.visibility import visibility
from avatarperfect_cli.stages.workspace_data import reference_pose, transl_offset
from avatarperfect_cli.training import metrics

WHITE = torch.ones(3)
CONDITIONS = ("initial", "video-only", "ap-exact", "ap-paper-objective", "ap-flat", "ap-keep-shapes", "random", "canonical", "erase-center", "erase-splat")
# condition: (body pose, painting style, refine --keep-shapes, suggest --exposure-poses)
EXPOSURE_POSES = SuggestConfig().exposure_poses
LOOP_CONDITIONS = {"ap-exact": ("optimise", "exact", False, EXPOSURE_POSES), "ap-paper-objective": ("optimise", "exact", False, 0),
                   "ap-flat": ("optimise", "flat", False, EXPOSURE_POSES), "ap-keep-shapes": ("optimise", "exact", True, EXPOSURE_POSES),
                   "random": ("random", "exact", False, EXPOSURE_POSES), "canonical": ("canonical", "exact", False, EXPOSURE_POSES)}  # fmt: skip
ORBIT_VIEWS = 12
SHOWN_FRAMES = (3, 12, 18, 27)  # held-out frames in the pictures: walking, arms raised, legs apart, squat


@dataclass
class HeldOut:
    """The held-out video with, per frame, the exact texture region of every pixel (`labels`, (T, H, W) int64
    indices into texture.REGIONS, -1 on the background) and the pixels of the surface the training video
    never showed (`unseen`, (T, H, W) bool)."""

    images: torch.Tensor
    masks: torch.Tensor
    labels: torch.Tensor
    unseen: torch.Tensor
    poses: list[PoseFile]

    def hidden(self, t: int, regions: Sequence[str] = HIDDEN_REGIONS) -> torch.Tensor:
        """(H, W) bool: frame t's pixels of the named texture regions (default: every hidden one)."""
        return torch.isin(self.labels[t], torch.tensor([REGION[name] for name in regions]))


def held_out(sample: Path, downscale: int) -> HeldOut:
    test = load_people_snapshot(sample / "test", downscale=downscale)
    train = load_people_snapshot(sample / "train", downscale=downscale)
    subject = SyntheticSubject.from_dataset(sample / "test")
    unseen_faces = subject.unseen_faces(train.body_pose, train.transl, train.camera)
    labels, unseen = [], []
    for t in range(len(test)):
        labels.append(torch.from_numpy(subject.render(test.body_pose[t], test.transl[t], test.camera).labels).long())
        ids = subject.face_ids(test.body_pose[t], test.transl[t], test.camera)
        unseen.append(torch.from_numpy((ids >= 0) & unseen_faces[ids.clip(min=0)]))
    poses = [PoseFile(test.body_pose[t], test.transl[t], test.camera) for t in range(len(test))]
    return HeldOut(test.images, test.masks, torch.stack(labels), torch.stack(unseen), poses)


def masked_psnr(render: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor) -> float:
    if not mask.any():
        return math.nan
    mse = float(((render.double() - truth.double()) ** 2)[mask].mean())
    return math.inf if mse == 0 else -10 * math.log10(mse)


def score(avatar: Avatar, data: HeldOut, offset: torch.Tensor) -> tuple[dict[str, float], list[torch.Tensor]]:
    """Mean held-out metrics of `avatar`, and its renders of SHOWN_FRAMES; the held-out translations move by
    the workspace's `offset` (3,) metres, as `evaluate` moves them."""
    rows, shown = [], []
    # squared error and values, over all frames' pixels together
    errors = {name: [0.0, 0] for name in ("hidden", "unseen", *HIDDEN_REGIONS)}
    with torch.no_grad():
        for t, pose in enumerate(data.poses):
            out = render_avatar(avatar, pose.body_pose, pose.transl + offset, pose.camera, WHITE)
            render, truth = out.image.clamp(0, 1), data.images[t]
            box = torch.zeros_like(data.masks[t])
            rows_any, cols_any = data.masks[t].any(dim=1).nonzero(), data.masks[t].any(dim=0).nonzero()
            box[int(rows_any[0]) : int(rows_any[-1]) + 1, int(cols_any[0]) : int(cols_any[-1]) + 1] = True
            rows.append({
                "iou": metrics.iou(out.alpha > 0.5, data.masks[t]), "psnr": metrics.psnr(render, truth),
                "ssim": metrics.ssim(render, truth), "psnr_bbox": masked_psnr(render, truth, box),
            })  # fmt: skip
            squared = ((render.double() - truth.double()) ** 2).sum(dim=-1)
            regions = {"hidden": data.hidden(t), "unseen": data.unseen[t]} | {name: data.hidden(t, [name]) for name in HIDDEN_REGIONS}
            for name, mask in regions.items():
                errors[name][0] += float(squared[mask].sum())
                errors[name][1] += int(mask.sum()) * 3
            if t in SHOWN_FRAMES:
                shown.append(render)
    mean = {key: statistics.fmean(row[key] for row in rows) for key in rows[0]}
    for name, (error, values) in errors.items():
        mean[f"psnr_{name}"] = -10 * math.log10(error / values) if values else math.nan
    return mean, shown


def training_psnr(avatar: Avatar, train: HeldOut, offset: torch.Tensor) -> float:
    with torch.no_grad():
        return statistics.fmean(
            metrics.psnr(render_avatar(avatar, p.body_pose, p.transl + offset, p.camera, WHITE).image.clamp(0, 1), train.images[t])
            for t, p in enumerate(train.poses)
        )


def worst_orbit_region(ws: Path, subject: SyntheticSubject, scratch: Path, user: UserConfig) -> tuple[Path, Path]:
    """SuperSplat's condition: the canonical pose seen from the worst of ORBIT_VIEWS horizontal orbit views
    (the most pixels the simulated user would paint background); returns (pose.json, region.png) with the
    region the simulated user paints background in that view."""
    from avatarperfect_cli.io import write_pose

    workspace = open_workspace(ws)
    avatar = Avatar.load(workspace.require_avatar())
    reference = reference_pose(workspace)
    camera = reference.camera
    up = -camera.world_to_camera[1, :3].float()
    center = reference.transl + avatar.rest_joints[0]
    best = None
    for k in range(ORBIT_VIEWS):
        spin = rotation_about(up, torch.tensor(2 * math.pi * k / ORBIT_VIEWS))
        view = camera.world_to_camera.clone().float()
        view[:3, :3] = view[:3, :3] @ spin.T
        view[:3, 3] = -view[:3, :3] @ (center + spin @ (camera.center.float() - center))
        pose = PoseFile(reference.body_pose, reference.transl, type(camera)(camera.K, view, camera.width, camera.height))
        with torch.no_grad():
            out = render_avatar(avatar, pose.body_pose, pose.transl, pose.camera, WHITE)
        image = torch.round(out.image.clamp(0, 1) * 255) / 255
        truth = pictured_truth(subject, pose, avatar.rest_joints, transl_offset(workspace), user.truth_pose)
        result = paint(image, out.alpha, truth, user)
        region = (result.stroke_weight >= 0.5) & (result.image >= 0.99).all(dim=-1) & (image < 0.99).any(dim=-1)
        if best is None or int(region.sum()) > best[0]:
            best = (int(region.sum()), pose, region)
    assert best is not None
    write_pose(scratch / "orbit_pose.json", best[1])
    write_image(scratch / "orbit_region.png", best[2].float()[..., None])
    return scratch / "orbit_pose.json", scratch / "orbit_region.png"


def run_condition(name: str, initial: Path, out: Path, sample: Path, subject: SyntheticSubject, train: HeldOut,
                  rounds: int, base_train_psnr: float, seed: int, user: UserConfig) -> dict:  # fmt: skip
    ws = out / name
    shutil.rmtree(ws, ignore_errors=True)
    shutil.copytree(initial, ws)
    round_seconds, train_drops = [], []
    scratch = out / f"{name}-scratch"
    scratch.mkdir(exist_ok=True)
    for round_index in range(rounds if name != "initial" else 0):
        start = time.perf_counter()
        user_seconds = 0.0
        round_seed = seed * rounds + round_index
        if name == "video-only":
            refine(ws, RefineSettings(seed=round_seed), progress=False)
        elif name in LOOP_CONDITIONS:
            mode, style, keep_shapes, exposure_poses = LOOP_CONDITIONS[name]
            visibility(ws, progress=False)
            search = SuggestConfig(body_pose=mode, exposure_poses=exposure_poses, seed=round_seed)
            suggest(ws, SuggestSettings(search), progress=False)
            user_start = time.perf_counter()
            painting = simulate_user(ws, sample, replace(user, style=style), output=scratch / "painted.png", progress=False, force=True)
            if painting.stats.painted_pixels:  # nothing wrong in view: no edit, the round's refine still runs (the paper, §8)
                apply_edit(ws, scratch / "painted.png", progress=False)
            user_seconds = time.perf_counter() - user_start
            refine(ws, RefineSettings(seed=round_seed, keep_shapes=keep_shapes), progress=False)
        else:
            user_start = time.perf_counter()
            pose, region = worst_orbit_region(ws, subject, scratch, user)
            user_seconds = time.perf_counter() - user_start
            if read_image(region, "L").max() < 0.5:
                round_seconds.append(time.perf_counter() - start - user_seconds)
                continue  # nothing the user would erase
            erase_region(ws, region, name.removeprefix("erase-"), pose, progress=False)
        round_seconds.append(time.perf_counter() - start - user_seconds)
        avatar = Avatar.load(open_workspace(ws).require_avatar())
        train_drops.append(training_psnr(avatar, train, transl_offset(open_workspace(ws))) - base_train_psnr)
        print(f"    {name} round {round_index + 1}: {round_seconds[-1]:.1f} s, training PSNR change {train_drops[-1]:+.3f} dB", flush=True)
    history = open_workspace(ws).manifest["history"]
    return {
        "workspace": ws,
        "deleted": sum(entry.get("deleted", 0) for entry in history),
        "seconds_per_round": statistics.fmean(round_seconds) if round_seconds else 0.0,
        "worst_training_change": min(train_drops) if train_drops else 0.0,
    }


def noisy_video(sample: Path, degrees: float, split: str = "train") -> Path:
    """SAMPLE/<split>-noisy: the split's video with estimated poses (`with_estimation_noise`, seed 0)."""
    noisy = sample / f"{split}-noisy"
    if not (noisy / "poses.npz").is_file():
        video = load_people_snapshot(sample / split)
        motion = with_estimation_noise(Motion(video.body_pose.double().numpy(), video.transl.double().numpy()), degrees)
        images = (video.images * 255.0).round().to(torch.uint8).numpy()  # the PNGs' own bytes
        write_people_snapshot(noisy, images, video.masks.numpy(), motion.body_pose, motion.transl, video.camera,
                              subject=json.loads((sample / split / "subject.json").read_text()))  # fmt: skip
    return noisy


def run_subject(preset: str, out: Path, rounds: int, resolution: int, iterations: int, conditions: Sequence[str],
                seed: int, images: Path | None, body: str = "fit", pose_noise: float = 0.0,
                user: UserConfig | None = None, max_gaussians: int | None = None) -> dict:  # fmt: skip
    """Every condition on the initial avatar of `seed`; writes the held-out picture to `images` (None: none)."""
    sample = out / "sample"
    if not (sample / "test" / "subject.json").is_file():
        make_sample(sample, preset, resolution)
    training = noisy_video(sample, pose_noise) if pose_noise > 0 else sample / "train"
    out = out / f"seed-{seed}"
    out.mkdir(parents=True, exist_ok=True)
    initial = out / "initial-ws"
    if not (initial / "workspace.json").is_file():
        start = time.perf_counter()
        fit = InitialFit(VideoSettings(), BodySettings(shape=body), iterations=iterations, seed=seed, refine_poses=pose_noise > 0)
        fit.max_gaussians = max_gaussians or fit.max_gaussians
        train_initial(training, initial, fit, force=True, progress=False)
        print(f"  {preset} seed {seed}: initial avatar trained in {time.perf_counter() - start:.0f} s", flush=True)
    data = held_out(sample, 1)
    train_video = load_people_snapshot(sample / "train", downscale=1)
    train = HeldOut(train_video.images, train_video.masks, torch.zeros(0), torch.zeros(0),
                    [PoseFile(train_video.body_pose[t], train_video.transl[t], train_video.camera) for t in range(len(train_video))])  # fmt: skip
    subject = SyntheticSubject.from_dataset(sample / "train")
    offset = transl_offset(open_workspace(initial))
    base_train_psnr = training_psnr(Avatar.load(open_workspace(initial).require_avatar()), train, offset)
    results, pictures = {}, {}
    for name in conditions:
        info = run_condition(name, initial, out, sample, subject, train, rounds, base_train_psnr, seed, user or UserConfig())
        mean, shown = score(Avatar.load(open_workspace(info.pop("workspace")).require_avatar()), data, offset)
        results[name] = {**mean, **info}
        pictures[name] = shown
        print(f"  {preset} seed {seed} {name}: PSNR {mean['psnr']:.2f} dB, hidden {mean['psnr_hidden']:.2f} dB, IoU {mean['iou']:.4f}", flush=True)
    if images is not None:
        truth = [data.images[t] for t in SHOWN_FRAMES]
        grid = torch.cat([torch.cat(truth, dim=1)] + [torch.cat(pictures[name], dim=1) for name in conditions], dim=0)
        images.mkdir(exist_ok=True)
        write_image(images / f"study_{preset}.png", torch.nn.functional.interpolate(
            grid.permute(2, 0, 1)[None], scale_factor=0.5, mode="area")[0].permute(1, 2, 0))  # fmt: skip
    return results


COLUMNS = (("iou", "IoU", "{:.4f}"), ("psnr", "PSNR", "{:.2f}"), ("ssim", "SSIM", "{:.4f}"), ("psnr_bbox", "PSNR box", "{:.2f}"),
           ("psnr_hidden", "PSNR hidden", "{:.2f}"), ("psnr_unseen", "PSNR unseen", "{:.2f}"), ("worst_training_change", "train dPSNR", "{:+.2f}"),
           ("deleted", "deleted", "{:.0f}"), ("seconds_per_round", "s/round", "{:.1f}"))  # fmt: skip


# the hidden-region PSNR split by region: the armpits are 8-23% of the held-out hidden-region pixels and ~40% of their error
REGION_COLUMNS = tuple((f"psnr_{name}", f"PSNR {name.replace('_', ' ')}", "{:.2f}") for name in HIDDEN_REGIONS)


def markdown_table(results: dict[str, dict], columns: Sequence[tuple[str, str, str]] = COLUMNS) -> str:
    lines = ["| condition | " + " | ".join(title for _, title, _ in columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for name, row in results.items():
        lines.append(f"| {name} | " + " | ".join(fmt.format(row[key]) for key, _, fmt in columns) + " |")
    return "\n".join(lines)


def combine(rows: Sequence[dict], conditions: Sequence[str]) -> dict[str, dict]:
    """Each condition's columns over several runs' results (seeds or subjects): the mean, except the worst
    training round, which is the worst of all (the bar is on every round)."""
    def pool(key: str) -> Callable[[Iterable[float]], float]:
        return min if key == "worst_training_change" else statistics.fmean

    return {name: {key: pool(key)(row[name][key] for row in rows) for key, _, _ in COLUMNS + REGION_COLUMNS} for name in conditions}


def gain_table(all_results: dict[str, dict[int, dict[str, dict]]], conditions: Sequence[str]) -> str:
    """Per condition and subject, the held-out PSNR and hidden-region PSNR changes from `initial` on the
    same seed's avatar: the mean over seeds and, with several seeds, their range."""
    presets = list(all_results)
    lines = ["| condition | " + " | ".join(f"{p}: PSNR / hidden" for p in presets) + " | mean: PSNR / hidden |",
             "|---" * (len(presets) + 2) + "|"]  # fmt: skip
    for name in conditions:
        if name == "initial":
            continue
        cells, means = [], {"psnr": [], "psnr_hidden": []}
        for preset in presets:
            parts = []
            for key in ("psnr", "psnr_hidden"):
                gains = [rows[name][key] - rows["initial"][key] for rows in all_results[preset].values()]
                means[key].append(statistics.fmean(gains))
                spread = f" ({min(gains):+.2f}..{max(gains):+.2f})" if len(gains) > 1 else ""
                parts.append(f"{statistics.fmean(gains):+.2f}{spread}")
            cells.append(" / ".join(parts))
        cells.append(f"**{statistics.fmean(means['psnr']):+.2f}** / **{statistics.fmean(means['psnr_hidden']):+.2f}**")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path)
    parser.add_argument("--presets", nargs="+", default=["default", "female", "tall"])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--resolution", type=int, default=512)
    parser.add_argument("--iterations", type=int, default=2000)
    parser.add_argument("--conditions", nargs="+", default=list(CONDITIONS), choices=CONDITIONS)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0], help="initial avatars per subject, one per seed")
    parser.add_argument("--body", choices=("fit", "exact"), default="fit",
                        help="the avatar's body: fitted to the masks from anny's middle phenotype (what a user gets), "
                             "or the subject's own (the best case, a reference row)")  # fmt: skip
    parser.add_argument("--pose-noise", type=float, default=0.0, metavar="DEG",
                        help="train on poses perturbed as a pose estimator's: DEG per joint axis, DEG/2 on the root, "
                             "DEG/2 cm on the translation; train-initial refines them (--refine-poses)")  # fmt: skip
    parser.add_argument("--max-gaussians", type=int, default=None, metavar="N",
                        help="cap the initial avatars' growth (train-initial --max-gaussians; default: train-initial's)")
    parser.add_argument("--user-outline-tolerance", type=float, default=UserConfig.outline_tolerance, metavar="SHARE",
                        help="the simulated user's outline tolerance (share of the image height; 0: pixel by pixel)")
    parser.add_argument("--user-truth-pose", choices=TRUTH_POSES, default=UserConfig.truth_pose,
                        help="the truth the simulated user compares with (simulate-user --truth-pose)")
    args = parser.parse_args()
    user = UserConfig(outline_tolerance=args.user_outline_tolerance, truth_pose=args.user_truth_pose)
    if "initial" not in args.conditions:
        args.conditions.insert(0, "initial")  # the gains are measured from it
    start = time.perf_counter()
    all_results: dict[str, dict[int, dict[str, dict]]] = {}
    for preset in args.presets:
        all_results[preset] = {}
        for seed in args.seeds:
            print(f"subject {preset}, seed {seed}", flush=True)
            images = args.out / "images" if seed == args.seeds[0] else None
            all_results[preset][seed] = run_subject(preset, args.out / preset, args.rounds, args.resolution, args.iterations,
                                                    args.conditions, seed, images, args.body, args.pose_noise, user,
                                                    args.max_gaussians)  # fmt: skip
            (args.out / "study.json").write_text(json.dumps(all_results, indent=2))
    per_subject = {preset: combine(list(all_results[preset].values()), args.conditions) for preset in args.presets}
    mean = combine(list(per_subject.values()), args.conditions)
    seeds = ", ".join(map(str, args.seeds))
    setting = f"body {args.body}, pose noise {args.pose_noise:g}°"
    text = [f"# Study: {len(args.presets)} subjects x seeds {seeds} x {args.rounds} rounds at {args.resolution}², {setting}, {time.perf_counter() - start:.0f} s\n"]
    text += [f"## Mean over {', '.join(args.presets)} (seeds {seeds}; train dPSNR: the worst round of all)\n", markdown_table(mean), ""]
    text += ["## Hidden regions one by one (mean)\n", markdown_table(mean, REGION_COLUMNS), ""]
    text += ["## Change from the initial avatar, per subject (mean over seeds, range)\n", gain_table(all_results, args.conditions), ""]
    for preset in args.presets:
        text += [f"## {preset} (mean over seeds {seeds})\n", markdown_table(per_subject[preset]), ""]
        if len(args.seeds) > 1:
            for seed in args.seeds:
                text += [f"### {preset}, seed {seed}\n", markdown_table(all_results[preset][seed]), ""]
    (args.out / "study.md").write_text("\n".join(text))
    print("\n".join(text))


if __name__ == "__main__":
    main()
