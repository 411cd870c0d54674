"""Rasterizer speed on the CPU: forward and forward+backward, the dense reference, JIT start-up.

    python -m benchmarks.rasterizer [--repeats 9] [--skip-reference] [--skip-jit]

Scene: N Gaussians on the surface of a human-sized figure (1.75 m tall, capsules for torso, head,
arms and legs) seen from 3 m, with flat disc-like Gaussians sized so that neighbours overlap, i.e.
a few pixels across at 512². Times are medians over the repeats after one warm-up run.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time

import torch

from avatarperfect_cli.render import Camera, look_at, rasterization
from avatarperfect_cli.render.reference import composite_dense, project_dense

# (centre of the bottom cap, centre of the top cap, radius), metres, +Y up.
CAPSULES = [
    ((0.0, 0.95, 0.0), (0.0, 1.40, 0.0), 0.15),  # torso
    ((0.0, 1.55, 0.0), (0.0, 1.65, 0.0), 0.10),  # head
    ((-0.10, 0.10, 0.0), (-0.10, 0.90, 0.0), 0.07),  # legs
    ((0.10, 0.10, 0.0), (0.10, 0.90, 0.0), 0.07),
    ((-0.20, 1.40, 0.0), (-0.55, 0.95, 0.0), 0.05),  # arms, A-pose
    ((0.20, 1.40, 0.0), (0.55, 0.95, 0.0), 0.05),
]


def human_scene(n: int, seed: int = 0) -> list[torch.Tensor]:
    """means, quats, scales, opacities, colours (float32) of n Gaussians on a capsule figure."""
    generator = torch.Generator().manual_seed(seed)
    bottoms = torch.tensor([c[0] for c in CAPSULES])
    tops = torch.tensor([c[1] for c in CAPSULES])
    radii = torch.tensor([c[2] for c in CAPSULES])
    areas = 2 * torch.pi * radii * (tops - bottoms).norm(dim=1) + 4 * torch.pi * radii**2
    part = torch.multinomial(areas / areas.sum(), n, replacement=True, generator=generator)
    along = torch.rand(n, 1, generator=generator)
    direction = torch.nn.functional.normalize(torch.randn(n, 3, generator=generator), dim=1)
    means = bottoms[part] + along * (tops[part] - bottoms[part]) + radii[part, None] * direction
    disc = torch.sqrt(areas.sum() / (torch.pi * n)) * 1.5
    scales = disc * torch.stack([1 + 0.3 * torch.rand(n, generator=generator), 1 + 0.3 * torch.rand(n, generator=generator), 0.2 * torch.ones(n)], 1)
    quats = torch.randn(n, 4, generator=generator)
    opacities = 0.5 + 0.5 * torch.rand(n, generator=generator)
    colors = torch.rand(n, 3, generator=generator)
    return [means, quats, scales, opacities, colors]


def camera(size: int) -> Camera:
    focal = 1.25 * size
    K = torch.tensor([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1]])
    view = look_at(torch.tensor([0.0, 0.9, 3.0]), torch.tensor([0.0, 0.88, 0.0]), torch.tensor([0.0, 1.0, 0.0]))
    return Camera(K, view, size, size)


def median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1000 * statistics.median(times)


def forward_fn(params, cam):
    def run():
        with torch.no_grad():
            rasterization(*params, cam)

    return run


def forward_backward_fn(params, cam):
    leaves = [p.clone().requires_grad_() for p in params]
    weights = torch.rand(cam.height, cam.width, 3)

    def run():
        out = rasterization(*leaves, cam)
        ((out.image * weights).sum() + out.alpha.sum()).backward()

    return run


def reference_forward_backward_ms(params, cam, chunk: int = 512) -> float:
    """The dense reference, forward+backward, processing pixel chunks to bound memory."""
    leaves = [p.clone().requires_grad_() for p in params]
    weights = torch.rand(cam.height * cam.width, 3)
    start = time.perf_counter()
    means2d, precision, depths, valid = project_dense(*leaves[:3], cam, 0.01, 1e10, 0.3)
    screen = [means2d.detach().requires_grad_(), precision.detach().requires_grad_()]
    order = torch.sort(depths.detach(), stable=True).indices
    ys, xs = torch.meshgrid(torch.arange(cam.height), torch.arange(cam.width), indexing="ij")
    pixels = torch.stack([xs, ys], -1).reshape(-1, 2).float() + 0.5
    background = torch.zeros(3)
    for begin in range(0, pixels.shape[0], chunk):
        color, alpha, _ = composite_dense(pixels[begin : begin + chunk], *screen, leaves[3], leaves[4], background, order, valid)
        ((color * weights[begin : begin + chunk]).sum() + alpha.sum()).backward()
    torch.autograd.backward([means2d, precision], [screen[0].grad, screen[1].grad])
    return 1000 * (time.perf_counter() - start)


JIT_PROBE = """
import time, torch
start = time.perf_counter()
from benchmarks.rasterizer import human_scene, camera, forward_backward_fn
forward_backward_fn(human_scene(1000), camera(64))()
print(time.perf_counter() - start)
"""


def jit_start_seconds(cache_dir: str) -> float:
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    result = subprocess.run([sys.executable, "-c", JIT_PROBE], env=env, cwd=root, capture_output=True, text=True, check=True)
    return float(result.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--skip-reference", action="store_true")
    parser.add_argument("--skip-jit", action="store_true")
    args = parser.parse_args()
    import numba

    print(f"torch {torch.__version__}, numba {numba.__version__}, threads: numba {numba.get_num_threads()}, torch {torch.get_num_threads()}")
    print(f"median of {args.repeats} runs after a warm-up\n")
    print("| N | image | forward ms | forward+backward ms |")
    print("|---:|---:|---:|---:|")
    rows = {}
    for size in (256, 512):
        for n in (10_000, 30_000, 100_000):
            params, cam = human_scene(n), camera(size)
            forward = median_ms(forward_fn(params, cam), args.repeats)
            both = median_ms(forward_backward_fn(params, cam), args.repeats)
            rows[(size, n)] = both
            print(f"| {n // 1000}k | {size}² | {forward:.1f} | {both:.1f} |")
    if not args.skip_reference:
        reference = reference_forward_backward_ms(human_scene(10_000), camera(256))
        fast = rows[(256, 10_000)]
        print(f"\ndense PyTorch reference, 256²/10k forward+backward: {reference / 1000:.1f} s "
              f"-> kernels are {reference / fast:.0f}x faster")  # fmt: skip
    if not args.skip_jit:
        with tempfile.TemporaryDirectory() as cache:
            cold = jit_start_seconds(cache)
            warm = jit_start_seconds(cache)
        print(f"\nfresh process, import + first forward+backward: cold JIT {cold:.1f} s, warm (cached) {warm:.1f} s")


if __name__ == "__main__":
    main()
