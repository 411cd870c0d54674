"""GPU against CPU, side by side in one run: the rasterizer and the stages of the loop.

    python -m benchmarks.gpu SAMPLE_DIR [--repeats 10] [--stage-repeats 3] [--devices cuda,cpu] [--profile]

SAMPLE_DIR: a 512² `avatarperfect make-sample` folder (train/ and test/). Measures, on each device:
  rasterizer       forward+backward of `rasterization()` (image and alpha into a weighted sum) at 512²/30k
                   and 1080²/100k Gaussians on the capsule figure of benchmarks/rasterizer.py
  train-initial    `train_initial()` with 2000 iterations on SAMPLE_DIR/train, in-process (the data
                   loading and the PLY write included, Python start and imports not); then the held-out
                   PSNR of the result on SAMPLE_DIR/test (rendered on the first device)
  visibility       `visibility()` over the 100 training frames of the first device's avatar
  suggest          `suggest()` with the default search, V already computed
  refine           `refine()` with 500 iterations after one simulated-user colour edit of a suggestion
Stage times are medians of --stage-repeats runs (train-initial: --train-repeats) after one warm-up
(CUDA context, gsplat's extension, numba's kernels); GPU times wait for the GPU (torch.cuda.synchronize).
--profile adds, on CUDA, one refine under cProfile, the time of each part of a training step (synchronised
after each part) and torch.profiler's top operators (to --profile-dir). Prints a markdown table last.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import torch

from avatarperfect_cli.datasets.people_snapshot import FrameRange
from avatarperfect_cli.render import rasterization
from avatarperfect_cli.stages.apply_edit import apply_edit
from avatarperfect_cli.stages.evaluate import evaluate
from avatarperfect_cli.stages.refine import RefineSettings, refine
from avatarperfect_cli.stages.simulate_user import simulate_user
from avatarperfect_cli.stages.suggest import SuggestSettings, suggest
from avatarperfect_cli.stages.train_initial import InitialFit, VideoSettings, train_initial
from avatarperfect_cli.stages.visibility import visibility
from benchmarks.rasterizer import camera, human_scene

ROOT = Path(__file__).resolve().parents[1]


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn: Callable[[], object], device: torch.device) -> float:
    """Seconds of one call, waiting for the device before and after."""
    synchronize(device)
    start = time.perf_counter()
    fn()
    synchronize(device)
    return time.perf_counter() - start


def median_seconds(fn: Callable[[], object], device: torch.device, repeats: int, warmup: int = 1) -> float:
    for _ in range(warmup):
        fn()
    return statistics.median(timed(fn, device) for _ in range(repeats))


def rasterizer_ms(size: int, n: int, device: torch.device, repeats: int) -> float:
    params = [p.to(device).requires_grad_() for p in human_scene(n)]
    cam = camera(size).to(device=device)
    weights = torch.rand(size, size, 3, device=device)

    def run() -> None:
        out = rasterization(*params, cam)
        ((out.image * weights).sum() + out.alpha.sum()).backward()

    return 1000 * median_seconds(run, device, repeats, warmup=2)


def held_out_psnr(ws: Path, sample: Path, device: torch.device) -> float:
    return evaluate(ws, sample / "test", frames=FrameRange(0, 29, 1), progress=False, device=device)["mean"]["psnr"]


def copy_workspace(source: Path, target: Path) -> Path:
    shutil.rmtree(target, ignore_errors=True)
    shutil.copytree(source, target)
    return target


def profile_training_step(sample: Path, device: torch.device, steps: int, out_dir: Path | None) -> list[tuple[str, float]]:
    """Median ms of each part of a training step at 512² on `device` (synchronised after each part)."""
    from avatarperfect_cli.avatar.model import Avatar
    from avatarperfect_cli.body import load_body_template
    from avatarperfect_cli.datasets import load_people_snapshot
    from avatarperfect_cli.training.losses import image_loss
    from avatarperfect_cli.training.optim import LearningRates, create_optimizers, set_learning_rates
    from avatarperfect_cli.training.strategy import DensifyConfig, DensifyStrategy
    from avatarperfect_cli.training.trainer import _supervised_region, video_views

    video = load_people_snapshot(sample / "train")
    template = load_body_template("anny", phenotype=video.subject["phenotype"])
    avatar = Avatar.from_template(template).to(device)
    views = [view.to(device) for view in video_views(video)]
    regions = [_supervised_region(view, 20) for view in views]
    with torch.no_grad():  # as the trainer keeps them
        transforms = [avatar.joint_transforms(view.body_pose, view.transl) for view in views]
    rates = LearningRates()
    optimizers = create_optimizers(avatar.params, rates)
    strategy = DensifyStrategy(DensifyConfig(refine_start=10**9))  # accumulate every step, never refine
    state = strategy.initialize_state()
    parts: dict[str, list[float]] = {}

    def part(name: str, fn: Callable[[], object]) -> object:
        synchronize(device)
        start = time.perf_counter()
        result = fn()
        synchronize(device)
        parts.setdefault(name, []).append(1000 * (time.perf_counter() - start))
        return result

    def step(index: int) -> None:
        view, (rows, cols) = views[index % len(views)], regions[index % len(views)]
        set_learning_rates(optimizers, rates, index)
        background = torch.rand(3).to(device)
        target = torch.where(view.foreground[..., None], view.image, background)
        means, quats = part("skinning (forward)", lambda: avatar.skin(transforms[index % len(views)]))
        out = part("rasterization (forward)", lambda: rasterization(
            means, quats, avatar.scales, avatar.opacities, avatar.sh, view.camera, sh_degree=avatar.active_sh_degree,
            background=background,
        ))  # fmt: skip
        loss = part("loss L1 + SSIM (forward)", lambda: image_loss(out.image[rows, cols], target[rows, cols]))
        strategy.step_pre_backward(avatar.params, optimizers, state, index, out)
        part("backward (all)", loss.backward)

        def optimise() -> None:
            for optimizer in optimizers.values():
                optimizer.step()
                optimizer.zero_grad(set_to_none=True)

        part("Adam (7 parameter groups)", optimise)
        part("densify statistics", lambda: strategy.step_post_backward(avatar.params, optimizers, state, index, out))

    for index in range(10):
        step(index)
    parts.clear()
    for index in range(steps):
        step(index)
    rows = [(name, statistics.median(values)) for name, values in parts.items()]
    if out_dir is not None and device.type == "cuda":
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            for index in range(20):
                step(index)
            synchronize(device)
        table = prof.key_averages().table(sort_by="self_cuda_time_total", row_limit=30)
        table_cpu = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=30)
        (out_dir / "profile_train_step.txt").write_text(table + "\n\n" + table_cpu)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sample", type=Path)
    parser.add_argument("--repeats", type=int, default=10, help="rasterizer runs per case")
    parser.add_argument("--stage-repeats", type=int, default=3)
    parser.add_argument("--train-repeats", type=int, default=1)
    parser.add_argument("--iterations", type=int, default=2000, help="train-initial iterations")
    parser.add_argument("--refine-iterations", type=int, default=500)
    parser.add_argument("--devices", default="cuda,cpu")
    parser.add_argument("--skip", default="", help="comma-separated: rasterizer,train,visibility,suggest,refine,cli")
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--profile-dir", type=Path, default=None, help="where torch.profiler's tables go")
    args = parser.parse_args()
    devices = [torch.device(name) for name in args.devices.split(",")]
    skip = set(filter(None, args.skip.split(",")))
    first = devices[0]
    import numba

    info = [f"torch {torch.__version__}", f"numba {numba.__version__} ({numba.get_num_threads()} threads)",
            f"CPU cores {os.cpu_count()}"]  # fmt: skip
    if torch.cuda.is_available():
        import gsplat

        info += [f"GPU {torch.cuda.get_device_name()}", f"gsplat {gsplat.__version__}"]
    print(", ".join(info), flush=True)
    rows: list[tuple[str, dict[str, str]]] = []

    def row(name: str, values: dict[torch.device, str]) -> None:
        rows.append((name, {str(d): v for d, v in values.items()}))
        print(f"{name}: " + ", ".join(f"{d} {v}" for d, v in values.items()), flush=True)

    if "rasterizer" not in skip:
        for size, n in ((512, 30_000), (1080, 100_000)):
            row(f"rasterizer forward+backward, {size}²/{n // 1000}k (ms)",
                {d: f"{rasterizer_ms(size, n, d, args.repeats):.1f}" for d in devices})  # fmt: skip

    scratch = Path(tempfile.mkdtemp(prefix="gpu-bench-"))
    trained: dict[torch.device, Path] = {}
    # warm-up: CUDA context, gsplat's extension and numba's kernels, on a tiny fit
    for device in devices:
        fit = InitialFit(video=VideoSettings(frames=FrameRange(0, 9, 1), resolution=128), iterations=20, device=device)
        train_initial(args.sample / "train", scratch / f"warm-{device.type}", fit, progress=False)
    if "train" not in skip:
        times, psnrs, counts = {}, {}, {}
        for device in devices:
            seconds = []
            for repeat in range(args.train_repeats):
                ws = scratch / f"trained-{device.type}-{repeat}"
                fit = InitialFit(iterations=args.iterations, device=device)
                seconds.append(timed(lambda: train_initial(args.sample / "train", ws, fit, progress=False), device))
            trained[device] = ws
            times[device] = f"{statistics.median(seconds):.1f}"
            psnrs[device] = f"{held_out_psnr(ws, args.sample, first):.2f}"
            from avatarperfect_cli.io.workspace import open_workspace

            counts[device] = f"{open_workspace(ws).manifest['history'][-1]['gaussians']:,}"
        row(f"train-initial, {args.iterations} iterations (s)", times)
        row("  held-out PSNR of that avatar, 30 test frames (dB)", psnrs)
        row("  Gaussians at the end", counts)
    else:
        fit = InitialFit(iterations=200, device=first)
        train_initial(args.sample / "train", scratch / "trained-short", fit, progress=False)
        trained[first] = scratch / "trained-short"
    base = trained[first]

    if "visibility" not in skip:
        row("visibility, 100 frames (s)", {
            d: f"{median_seconds(lambda: visibility(copy_workspace(base, scratch / 'vis'), progress=False, device=d), d, args.stage_repeats):.2f}"
            for d in devices
        })  # fmt: skip
    # V once, so that suggest measures the search alone
    visibility(base, progress=False, device=first)
    if "suggest" not in skip:
        row("suggest, default search, V computed (s)", {
            d: f"{median_seconds(lambda: suggest(copy_workspace(base, scratch / 'sug'), SuggestSettings(device=d), progress=False), d, args.stage_repeats):.2f}"
            for d in devices
        })  # fmt: skip
    if "refine" not in skip:
        edited = copy_workspace(base, scratch / "edited")
        suggest(edited, SuggestSettings(device=first), progress=False)
        simulate_user(edited, output=scratch / "painted.png", progress=False, force=True)
        apply_edit(edited, scratch / "painted.png", progress=False)
        visibility(edited, progress=False, device=first)
        settings = {d: RefineSettings(iterations=args.refine_iterations, device=d) for d in devices}
        row(f"refine, {args.refine_iterations} iterations, 1 colour edit (s)", {
            d: f"{median_seconds(lambda: refine(copy_workspace(edited, scratch / 'ref'), settings[d], progress=False), d, args.stage_repeats):.2f}"
            for d in devices
        })  # fmt: skip
        if "cli" not in skip:
            walls = {}
            for d in devices:
                copy_workspace(edited, scratch / "cli")
                command = [sys.executable, "-m", "avatarperfect_cli", "refine", str(scratch / "cli"), "--device", d.type,
                           "--iterations", str(args.refine_iterations)]  # fmt: skip
                start = time.perf_counter()
                subprocess.run(command, check=True, capture_output=True, cwd=ROOT)
                walls[d] = f"{time.perf_counter() - start:.2f}"
            row("  `avatarperfect refine` command, wall, Python start and imports included (s)", walls)

    if args.profile and "refine" not in skip and any(d.type == "cuda" for d in devices):
        import cProfile
        import pstats

        cuda = torch.device("cuda")
        profiler = cProfile.Profile()
        ws = copy_workspace(edited, scratch / "ref")
        profiler.runcall(lambda: refine(ws, RefineSettings(iterations=args.refine_iterations, device=cuda), progress=False))
        print("\none CUDA refine under cProfile, by cumulative time:")
        pstats.Stats(profiler).sort_stats("cumulative").print_stats(18)
    if args.profile and any(d.type == "cuda" for d in devices):
        print("\ntraining step parts at 512² on CUDA (median ms, synchronised after each part):")
        for name, ms in profile_training_step(args.sample, torch.device("cuda"), 100, args.profile_dir):
            print(f"  {name}: {ms:.2f}")

    shutil.rmtree(scratch, ignore_errors=True)
    names = [str(d) for d in devices]
    print("\n| what | " + " | ".join(names) + " |")
    print("|---|" + "---:|" * len(names))
    for name, values in rows:
        print(f"| {name} | " + " | ".join(values.get(n, "") for n in names) + " |")


if __name__ == "__main__":
    main()
