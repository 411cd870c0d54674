"""The pose fit: the acceleration against its closed form, and poses perturbed like a pose estimator's
brought back toward the committed sample's true ones."""

from __future__ import annotations

from pathlib import Path

import torch

from avatarperfect_cli.body import forward_kinematics, load_body_template
from avatarperfect_cli.datasets import FrameRange, VideoDataset, load_people_snapshot
from avatarperfect_cli.training.pose_fit import PoseFitConfig, acceleration, fit_poses_to_masks

SAMPLE = Path(__file__).resolve().parents[2] / "examples" / "sample" / "train"


def test_acceleration_of_a_parabola_at_uneven_times() -> None:
    times = torch.tensor([0.0, 1.0, 3.0, 4.0, 7.0, 8.0], dtype=torch.float64)
    positions = torch.stack([3.0 * times**2 - times, -0.5 * times**2], dim=1)  # (T, 2)
    expected = torch.tensor([6.0, -1.0], dtype=torch.float64).expand(len(times) - 2, 2)
    torch.testing.assert_close(acceleration(positions, times), expected)


def _posed_joints(template, body_pose: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
    transforms = forward_kinematics(body_pose, template.rest_joints, transl)
    return (transforms[..., :3, :3] @ template.rest_joints[:, :, None] + transforms[..., :3, 3:])[..., 0]


def test_noisy_poses_are_brought_back_toward_the_truth() -> None:
    """3 degrees of noise per joint axis (half on the root) and 1.5 cm on the translations, over 30
    consecutive frames: the fit at 96 pixels more than halves the posed joints' distance from the truth."""
    video = load_people_snapshot(SAMPLE, FrameRange(0, 29, 1), downscale=1)
    template = load_body_template("anny", phenotype=video.subject["phenotype"])
    generator = torch.Generator().manual_seed(3)
    noise = torch.randn(video.body_pose.shape, generator=generator) * torch.deg2rad(torch.tensor(3.0))
    noise[:, 0] *= 0.5
    noisy = VideoDataset(**{**vars(video), "body_pose": video.body_pose + noise,
                            "transl": video.transl + 0.015 * torch.randn(video.transl.shape, generator=generator)})  # fmt: skip
    config = PoseFitConfig(resolution=96, points=1000, contour_pixels=150, steps=120)
    fit = fit_poses_to_masks(noisy, template, config)
    truth = _posed_joints(template, video.body_pose, video.transl)
    before = (_posed_joints(template, noisy.body_pose, noisy.transl) - truth).norm(dim=-1).mean()
    after = (_posed_joints(template, fit.body_pose, fit.transl) - truth).norm(dim=-1).mean()
    assert float(after) < 0.5 * float(before), (float(before), float(after))
    assert fit.loss < fit.start_loss
    assert fit.body_pose.shape == video.body_pose.shape and fit.transl.shape == video.transl.shape
