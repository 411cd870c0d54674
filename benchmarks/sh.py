"""SH colour evaluation on the CPU: the numba kernels against the dense torch `eval_sh`, side by side.

    python -m benchmarks.sh [--repeats 31]

Forward + backward (gradients to the coefficients and the directions, as a training step asks) of N
Gaussians' colours; the two versions alternate call by call, so the ratio is robust to this VM's drift.
Prints median milliseconds and the median of the per-pair ratios.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import torch

from avatarperfect_cli.gaussians import eval_sh
from avatarperfect_cli.gaussians.sh_kernels import eval_sh_cpu


def forward_backward(evaluate: Callable, sh: torch.Tensor, dirs: torch.Tensor, degree: int, upstream: torch.Tensor) -> Callable[[], None]:
    def run() -> None:
        sh.grad = dirs.grad = None
        evaluate(sh, dirs, degree).backward(upstream)

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=31)
    args = parser.parse_args()
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}; median of {args.repeats} interleaved pairs\n")
    print("| N | degree | torch ms | numba ms | numba / torch |")
    print("|---:|---:|---:|---:|---:|")
    generator = torch.Generator().manual_seed(0)
    for n in (10_000, 48_000, 100_000):
        for degree in (1, 3):
            sh = torch.randn(n, (degree + 1) ** 2, 3, generator=generator).requires_grad_()
            dirs = torch.randn(n, 3, generator=generator).requires_grad_()
            upstream = torch.randn(n, 3, generator=generator)
            runs = [forward_backward(f, sh, dirs, degree, upstream) for f in (eval_sh, eval_sh_cpu)]
            for run in runs:
                run()  # warm-up (and the kernels' compilation or cache load)
            times: list[list[float]] = [[], []]
            for _ in range(args.repeats):
                for run, record in zip(runs, times):
                    start = time.perf_counter()
                    run()
                    record.append(time.perf_counter() - start)
            ratio = statistics.median(b / a for a, b in zip(*times))
            torch_ms, numba_ms = (1e3 * statistics.median(t) for t in times)
            print(f"| {n:,} | {degree} | {torch_ms:.2f} | {numba_ms:.2f} | {ratio:.2f} |")


if __name__ == "__main__":
    main()
