"""The pose fits: the acceleration against its closed form, and poses perturbed like a pose estimator's
brought back toward the committed sample's true ones by the masks and by the images."""

from __future__ import annotations

from pathlib import Path

import torch

from avatarperfect_cli.body import BodyTemplate, forward_kinematics, load_body_template
from avatarperfect_cli.datasets import FrameRange, VideoDataset, load_people_snapshot
from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.gaussians import rgb_to_sh
from avatarperfect_cli.training.pose_fit import ImagePoseConfig, PoseFit, PoseFitConfig, acceleration, fit_poses_to_images, fit_poses_to_masks
from avatarperfect_cli.training.silhouette import SkinnedPoints

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
    fit = fit_poses_to_masks(noisy, SkinnedPoints.of_template(template, config.points), config)
    truth = _posed_joints(template, video.body_pose, video.transl)
    before = (_posed_joints(template, noisy.body_pose, noisy.transl) - truth).norm(dim=-1).mean()
    after = (_posed_joints(template, fit.body_pose, fit.transl) - truth).norm(dim=-1).mean()
    assert float(after) < 0.5 * float(before), (float(before), float(after))
    assert fit.loss < fit.start_loss
    assert fit.body_pose.shape == video.body_pose.shape and fit.transl.shape == video.transl.shape


def _patterned_avatar_and_its_frames() -> tuple[BodyTemplate, Avatar, VideoDataset]:
    """An avatar on the sample's own body with a colour pattern, and six of the sample's frames: its renders
    at the sample's poses, with their alpha as the masks."""
    video = load_people_snapshot(SAMPLE, FrameRange(0, 59, 10), downscale=2)
    template = load_body_template("anny", phenotype=video.subject["phenotype"])
    avatar = Avatar.from_template(template)
    with torch.no_grad():
        avatar.params["sh_dc"][:] = rgb_to_sh(0.5 + 0.4 * torch.sin(25.0 * avatar.params["means"]))[:, None]
        renders = [render_avatar(avatar, video.body_pose[t], video.transl[t], video.camera, torch.ones(3)) for t in range(len(video))]
    images = torch.stack([render.image for render in renders]).clamp(0, 1)
    return template, avatar, VideoDataset(**{**vars(video), "images": images, "masks": torch.stack([render.alpha > 0.5 for render in renders])})


def test_poses_moved_off_the_images_are_put_back() -> None:
    """An avatar on the sample's own body, with a colour pattern, rendered at six of the sample's poses as the
    frames; the poses then moved (the root turned 4 degrees and moved 3 cm): the image fit brings the posed
    joints back within a third of their error, and leaves the avatar trainable."""
    template, avatar, video = _patterned_avatar_and_its_frames()
    generator = torch.Generator().manual_seed(5)
    pose_noise = torch.zeros_like(video.body_pose)
    pose_noise[:, 0] = torch.randn(len(video), 3, generator=generator) * torch.deg2rad(torch.tensor(4.0))
    transl_noise = torch.nn.functional.normalize(torch.randn(len(video), 3, generator=generator), dim=1) * 0.03
    moved = VideoDataset(**{**vars(video), "body_pose": video.body_pose + pose_noise, "transl": video.transl + transl_noise})
    fit = fit_poses_to_images(avatar, moved, ImagePoseConfig(resolution=128, steps=40))
    truth = _posed_joints(template, video.body_pose, video.transl)
    before = (_posed_joints(template, moved.body_pose, moved.transl) - truth).norm(dim=-1).mean()
    after = (_posed_joints(template, fit.body_pose, fit.transl) - truth).norm(dim=-1).mean()
    assert float(after) < float(before) / 3, (float(before), float(after))
    assert fit.loss < fit.start_loss
    assert all(parameter.requires_grad for parameter in avatar.params.values())


def test_each_frame_starts_from_the_pose_its_image_prefers() -> None:
    """Every other frame's given pose is the truth and its other start is turned 25 degrees and moved 10 cm;
    the rest the other way round. With no steps, the fit returns the start it chose: the truth in every frame."""
    _, avatar, video = _patterned_avatar_and_its_frames()
    wrong_pose, wrong_transl = video.body_pose.clone(), video.transl + torch.tensor([0.1, 0.0, 0.0])
    wrong_pose[:, 0, 1] += torch.deg2rad(torch.tensor(25.0))
    given_is_true = (torch.arange(len(video)) % 2 == 0)
    pick = lambda true, wrong, first: torch.where(given_is_true.reshape(-1, *[1] * (true.dim() - 1)) == first, true, wrong)  # noqa: E731
    given = VideoDataset(**{**vars(video), "body_pose": pick(video.body_pose, wrong_pose, True), "transl": pick(video.transl, wrong_transl, True)})
    other = PoseFit(pick(video.body_pose, wrong_pose, False), pick(video.transl, wrong_transl, False), 0.0, 0.0)
    fit = fit_poses_to_images(avatar, given, ImagePoseConfig(resolution=128, steps=0), other_start=other)
    torch.testing.assert_close(fit.body_pose, video.body_pose)
    torch.testing.assert_close(fit.transl, video.transl)
