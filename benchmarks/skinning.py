"""Skinning speed on the CPU: Gaussians (the numba kernel against the torch path) and points over many poses
(the body and pose fits: the sparse numba kernels against one matrix product), forward and forward+backward.

    python -m benchmarks.skinning [--repeats 15] [--threads T]

`skin_gaussians` (blend 24 joint transforms, pose means, turn each orientation by the polar rotation of its
blended 3x3) in float32 for N = 30k and 100k Gaussians, each weighted mostly to 1 to 3 joints (a softmax of
sparse logits), under the transforms of a random pose (0.5 rad per joint) of a random skeleton.
Forward+backward: gradients w.r.t. means, quats, weights and transforms from a random upstream gradient.
Times are medians over the repeats after one warm-up run, in one process; --threads sets torch's thread count
(the numba kernel itself is single-threaded; blending the transforms is a torch matmul).

Points: `skin_points` of N points, each weighted to 1 to 3 joints, under the forward kinematics of F random
poses, as the fits run it (2000 points over 100 frames, 5000 over 24); forward+backward: gradients w.r.t. the
points and the transforms. The sparse kernels run over the cores.
"""

from __future__ import annotations

import argparse

import torch

from avatarperfect_cli.body import NUM_JOINTS, SMPL_PARENTS, forward_kinematics, skin_gaussians, skin_points
from avatarperfect_cli.body.skeleton import skin_points_product
from benchmarks.rasterizer import median_ms


def _skeleton(generator: torch.Generator) -> torch.Tensor:
    """(24, 3) rest joints: each a random 15 cm step from its parent."""
    joints = torch.zeros(NUM_JOINTS, 3)
    joints[0] = torch.tensor([0.0, 0.9, 0.0])
    for joint, parent in enumerate(SMPL_PARENTS[1:], start=1):
        joints[joint] = joints[parent] + 0.15 * torch.randn(3, generator=generator)
    return joints


def skinning_scene(n: int, seed: int = 0) -> list[torch.Tensor]:
    """means (n, 3), quats (n, 4), weights (n, 24) and posed transforms (24, 4, 4), float32."""
    generator = torch.Generator().manual_seed(seed)
    joints = _skeleton(generator)
    pose = 0.5 * torch.randn(1, NUM_JOINTS, 3, generator=generator)
    transforms = forward_kinematics(pose, joints, torch.zeros(1, 3))[0]
    logits = torch.zeros(n, NUM_JOINTS)
    favoured = torch.randint(0, NUM_JOINTS, (n, 3), generator=generator)
    logits.scatter_(1, favoured, 8.0 * torch.rand(n, 3, generator=generator))
    weights = torch.softmax(logits - 4.0 * (logits == 0), dim=-1)
    means = joints[favoured[:, 0]] + 0.1 * torch.randn(n, 3, generator=generator)
    quats = torch.randn(n, 4, generator=generator)
    return [means, quats, weights, transforms]


def point_scene(n: int, frames: int, seed: int = 0) -> list[torch.Tensor]:
    """points (n, 3), weights (n, 24) with 1 to 3 nonzero per point and transforms (frames, 24, 4, 4), float32."""
    generator = torch.Generator().manual_seed(seed)
    joints = _skeleton(generator)
    weights = torch.zeros(n, NUM_JOINTS)
    weights.scatter_(1, torch.randint(0, NUM_JOINTS, (n, 3), generator=generator), torch.rand(n, 3, generator=generator))
    weights = weights * (torch.rand(n, NUM_JOINTS, generator=generator) < 0.6)
    weights[:, 0] += 1e-3  # no point without a joint
    pose = 0.5 * torch.randn(frames, NUM_JOINTS, 3, generator=generator)
    transforms = forward_kinematics(pose, joints, torch.randn(frames, 3, generator=generator))
    points = joints[weights.argmax(dim=1)] + 0.1 * torch.randn(n, 3, generator=generator)
    return [points, weights / weights.sum(dim=1, keepdim=True), transforms]


def point_fns(scene: list[torch.Tensor], skin):
    """The forward and the forward+backward of `skin` on a `point_scene`."""
    points, weights, transforms = scene
    leaves = points.clone().requires_grad_(), transforms.clone().requires_grad_()
    grad = torch.randn(len(transforms), len(points), 3)

    def forward():
        with torch.no_grad():
            skin(points, weights, transforms)

    def both():
        skin(leaves[0], weights, leaves[1]).backward(grad)

    return forward, both


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
    print("\n| points × poses | skinning | forward ms | forward+backward ms |")
    print("|---:|---|---:|---:|")
    for n, frames in ((2000, 100), (5000, 24)):
        scene = point_scene(n, frames)
        for label, skin in (("sparse kernels", skin_points), ("matrix product", skin_points_product)):
            forward, both = point_fns(scene, skin)
            print(f"| {n} × {frames} | {label} | {median_ms(forward, args.repeats):.1f} | {median_ms(both, args.repeats):.1f} |")


if __name__ == "__main__":
    main()
