"""Gaussian skinning speed on the CPU: the numba kernel against the torch path, forward and forward+backward.

    python -m benchmarks.skinning [--repeats 15] [--threads T]

`skin_gaussians` (blend 24 joint transforms, pose means, turn each orientation by the polar rotation of its
blended 3x3) in float32 for N = 30k and 100k Gaussians, each weighted mostly to 1 to 3 joints (a softmax of
sparse logits), under the transforms of a random pose (0.5 rad per joint) of a random skeleton.
Forward+backward: gradients w.r.t. means, quats, weights and transforms from a random upstream gradient.
Times are medians over the repeats after one warm-up run, in one process; --threads sets torch's thread count
(the numba kernel itself is single-threaded; blending the transforms is a torch matmul).
"""

from __future__ import annotations

import argparse

import torch

from avatarperfect_cli.body import NUM_JOINTS, SMPL_PARENTS, forward_kinematics, skin_gaussians
from benchmarks.rasterizer import median_ms


def skinning_scene(n: int, seed: int = 0) -> list[torch.Tensor]:
    """means (n, 3), quats (n, 4), weights (n, 24) and posed transforms (24, 4, 4), float32."""
    generator = torch.Generator().manual_seed(seed)
    joints = torch.zeros(NUM_JOINTS, 3)
    joints[0] = torch.tensor([0.0, 0.9, 0.0])
    for joint, parent in enumerate(SMPL_PARENTS[1:], start=1):
        joints[joint] = joints[parent] + 0.15 * torch.randn(3, generator=generator)
    pose = 0.5 * torch.randn(1, NUM_JOINTS, 3, generator=generator)
    transforms = forward_kinematics(pose, joints, torch.zeros(1, 3))[0]
    logits = torch.zeros(n, NUM_JOINTS)
    favoured = torch.randint(0, NUM_JOINTS, (n, 3), generator=generator)
    logits.scatter_(1, favoured, 8.0 * torch.rand(n, 3, generator=generator))
    weights = torch.softmax(logits - 4.0 * (logits == 0), dim=-1)
    means = joints[favoured[:, 0]] + 0.1 * torch.randn(n, 3, generator=generator)
    quats = torch.randn(n, 4, generator=generator)
    return [means, quats, weights, transforms]


def forward_fn(scene: list[torch.Tensor], backend: str):
    def run():
        with torch.no_grad():
            skin_gaussians(*scene, backend=backend)

    return run


def forward_backward_fn(scene: list[torch.Tensor], backend: str):
    leaves = [tensor.clone().requires_grad_() for tensor in scene]
    grad_means, grad_quats = torch.randn_like(scene[0]), torch.randn_like(scene[1])

    def run():
        posed_means, posed_quats = skin_gaussians(*leaves, backend=backend)
        torch.autograd.backward([posed_means, posed_quats], [grad_means, grad_quats])

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    import numba

    print(f"torch {torch.__version__}, numba {numba.__version__}, threads: torch {torch.get_num_threads()} "
          "(the numba kernel runs on one)")  # fmt: skip
    print(f"median of {args.repeats} runs after a warm-up, float32\n")
    print("| N | backend | forward ms | forward+backward ms |")
    print("|---:|---|---:|---:|")
    for n in (30_000, 100_000):
        scene = skinning_scene(n)
        for backend in ("numba", "torch"):
            forward = median_ms(forward_fn(scene, backend), args.repeats)
            both = median_ms(forward_backward_fn(scene, backend), args.repeats)
            print(f"| {n // 1000}k | {backend} | {forward:.1f} | {both:.1f} |")


if __name__ == "__main__":
    main()
