"""Per-frame pose refinement recovers perturbed poses from the images."""

from __future__ import annotations

import torch

from avatarperfect_cli.training.pose_refinement import PoseRefinementConfig, PoseRefiner
from avatarperfect_cli.training.trainer import TrainConfig, TrainingView, train

from .test_trainer import coloured_avatar, video_of


def test_refinement_recovers_perturbed_global_orientation():
    truth = video_of(coloured_avatar())
    errors = [0.15, -0.15, 0.15, -0.15]  # zero mean: a common offset could be absorbed by the avatar
    noisy = []
    for view, error in zip(truth, errors):
        pose = view.body_pose.clone()
        pose[0, 1] += error
        noisy.append(TrainingView(view.image, view.foreground, pose, view.transl, view.camera))
    refiner = PoseRefiner(len(noisy), PoseRefinementConfig(learning_rate=5e-3, start_step=0))
    train(coloured_avatar(), noisy, config=TrainConfig(iterations=120), progress=False, pose_refiner=refiner)
    refined, _ = refiner.refined(torch.stack([v.body_pose for v in noisy]), torch.stack([v.transl for v in noisy]))
    true_yaw = torch.stack([v.body_pose[0, 1] for v in truth])
    before = (torch.tensor(errors)).abs().mean()
    after = (refined[:, 0, 1] - true_yaw).abs().mean()
    assert after < 0.3 * before, (float(before), float(after))


def test_offsets_are_unused_before_the_start_step():
    refiner = PoseRefiner(2, PoseRefinementConfig(start_step=10))
    with torch.no_grad():
        refiner.pose_offsets[1] = 1.0
    pose, transl = torch.zeros(24, 3), torch.zeros(3)
    assert torch.equal(refiner.pose(1, pose, transl, step=9)[0], pose)
    assert torch.equal(refiner.pose(1, pose, transl, step=10)[0], torch.ones(24, 3))


def test_a_step_moves_only_the_drawn_frame_as_adam_on_that_frame_alone():
    refiner = PoseRefiner(3, PoseRefinementConfig(learning_rate=0.01, start_step=0))
    reference = torch.zeros(24 * 3 + 3, requires_grad=True)
    adam = torch.optim.Adam([reference], lr=0.01, eps=1e-8)
    generator = torch.Generator().manual_seed(0)
    for _ in range(5):
        weights = torch.randn(24 * 3 + 3, generator=generator)
        pose, transl = refiner.pose(1, torch.zeros(24, 3), torch.zeros(3), step=0)
        (torch.cat([pose.flatten(), transl]) * weights).sum().backward()
        refiner.step(1, step=0)
        adam.zero_grad()
        (reference * weights).sum().backward()
        adam.step()
    moved = torch.cat([refiner.pose_offsets[1].detach().flatten(), refiner.transl_offsets[1].detach()])
    torch.testing.assert_close(moved, reference.detach(), rtol=1e-5, atol=1e-7)
    assert not refiner.pose_offsets[[0, 2]].any() and not refiner.transl_offsets[[0, 2]].any()
    assert refiner.pose_offsets.grad is None
