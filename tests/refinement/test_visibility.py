"""Accumulated Gaussian visibility V (paper §6.2) against a dense float64 brute force on a small rigid scene."""

from __future__ import annotations

import math

import pytest
import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.body import load_body_template
from avatarperfect_cli.io.pose_json import PoseFile
from avatarperfect_cli.refinement.visibility import (
    accumulate_visibility,
    combine_visibility,
    gaussian_visibility,
    painted_visibility,
    suggestion_weights,
)
from avatarperfect_cli.render import Camera, look_at
from avatarperfect_cli.render.reference import rasterization_reference

WIDTH, HEIGHT = 24, 20
UP = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)


def rigid_avatar(n: int, seed: int, dtype: torch.dtype = torch.float64, spread: float = 0.5) -> Avatar:
    """n random Gaussians around the rest pelvis, every one skinned to joint 0 only (posing is rigid)."""
    generator = torch.Generator().manual_seed(seed)
    rest_joints = load_body_template("anny").rest_joints.double()

    def uniform(low: float, high: float, *shape: int) -> torch.Tensor:
        return low + (high - low) * torch.rand(*shape, generator=generator, dtype=torch.float64)

    skin_logits = torch.full((n, 24), -1e9, dtype=torch.float64)
    skin_logits[:, 0] = 0.0
    params = {
        "means": rest_joints[0] + uniform(-spread, spread, n, 3),
        "quats": torch.randn(n, 4, generator=generator, dtype=torch.float64),
        "log_scales": uniform(-3.5, -2.0, n, 3),
        "opacity_logits": uniform(-2.0, 3.0, n),
        "sh_dc": uniform(-1.0, 1.0, n, 1, 3),
        "sh_rest": torch.zeros(n, 0, 3, dtype=torch.float64),
        "skin_logits": skin_logits,
    }
    return Avatar({k: v.to(dtype) for k, v in params.items()}, rest_joints.to(dtype), sh_degree=0)


def rotation_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """(3, 3) float64 rotation of the axis-angle `rotvec` (3,), non-zero (Rodrigues' formula)."""
    rotvec = rotvec.double()
    angle = float(rotvec.norm())
    x, y, z = (rotvec / angle).tolist()
    cross = torch.tensor([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross


def rigid_pose(avatar: Avatar, view: PoseFile) -> tuple[torch.Tensor, torch.Tensor]:
    """Independent float64 posing of a joint-0-only avatar: x -> R (x - j0) + j0 + transl, q -> q_R * q."""
    rotvec = view.body_pose[0].double()
    angle = float(rotvec.norm())
    j0 = avatar.rest_joints[0].double()
    means = (avatar.params["means"].detach().double() - j0) @ rotation_matrix(rotvec).T + j0 + view.transl.double()
    w1, (x1, y1, z1) = math.cos(angle / 2), (math.sin(angle / 2) * rotvec / angle).tolist()
    w2, x2, y2, z2 = avatar.params["quats"].detach().double().unbind(-1)
    quats = torch.stack([
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ], dim=-1)  # fmt: skip
    return means, quats


def random_views(count: int, seed: int, center: torch.Tensor, dtype: torch.dtype = torch.float64) -> list[PoseFile]:
    """`count` views: a random global orientation and translation, a camera 2.5 m away on a random bearing."""
    generator = torch.Generator().manual_seed(seed)
    views = []
    for _ in range(count):
        body_pose = torch.zeros(24, 3, dtype=torch.float64)
        body_pose[0] = torch.randn(3, generator=generator, dtype=torch.float64)
        transl = 0.05 * torch.randn(3, generator=generator, dtype=torch.float64)
        bearing = 2 * math.pi * float(torch.rand((), generator=generator, dtype=torch.float64))
        height = 0.8 * float(torch.rand((), generator=generator, dtype=torch.float64)) - 0.4
        eye = center + torch.tensor([2.5 * math.sin(bearing), height, 2.5 * math.cos(bearing)], dtype=torch.float64)
        K = torch.tensor([[60.0, 0, WIDTH / 2 + 0.3], [0, 62.0, HEIGHT / 2 - 0.2], [0, 0, 1]], dtype=torch.float64)
        camera = Camera(K, look_at(eye, center, UP), WIDTH, HEIGHT)
        views.append(PoseFile(body_pose.to(dtype), transl.to(dtype), camera))
    return views


def brute_force_visibility(avatar: Avatar, view: PoseFile) -> torch.Tensor:
    """(N,) float64 sum over pixels of T * alpha per Gaussian, by the dense reference renderer."""
    means, quats = rigid_pose(avatar, view)
    p = avatar.params
    scales = torch.exp(p["log_scales"].detach().double())
    opacities = torch.sigmoid(p["opacity_logits"].detach().double())
    colors = torch.zeros(len(avatar), 1, dtype=torch.float64)
    return rasterization_reference(means, quats, scales, opacities, colors, view.camera.to(dtype=torch.float64))[3]


def brute_force_combined(video: list[torch.Tensor], edits: list[torch.Tensor], edit_weight: float) -> torch.Tensor:
    """(1 - w) * mean of the video's per-view visibilities + w * mean of the edits' (the video's alone without
    edits)."""
    video_mean = sum(video) / len(video)
    if not edits:
        return video_mean
    return (1 - edit_weight) * video_mean + edit_weight * sum(edits) / len(edits)


def brute_force_per_view(avatar: Avatar, views: list[PoseFile]) -> list[torch.Tensor]:
    return [brute_force_visibility(avatar, view) for view in views]


@pytest.fixture(scope="module")
def scene():
    """The avatar, 3 video views, 2 edit views and the brute-force visibilities of each view."""
    avatar = rigid_avatar(48, seed=0)
    video = random_views(3, seed=1, center=avatar.rest_joints[0])
    edits = random_views(2, seed=2, center=avatar.rest_joints[0])
    return avatar, video, edits, (brute_force_per_view(avatar, video), brute_force_per_view(avatar, edits))


def test_brute_force_scene_is_not_trivial(scene) -> None:
    _, _, _, (video, edits) = scene
    per_view = torch.stack(video + edits)
    assert (per_view > 0).sum(dim=1).min() >= 10, "every view should see a good share of the Gaussians"
    assert (per_view == 0).any(), "some Gaussians should be hidden or off-image in some view"
    assert (per_view[:3].mean(0) - per_view[3:].mean(0)).abs().max() > 1.0, "video and edits should see differently"


@pytest.mark.parametrize("edit_weight", [0.01, 0.3])
def test_accumulated_visibility_matches_brute_force(scene, edit_weight: float) -> None:
    avatar, video, edits, brute = scene
    expected = brute_force_combined(*brute, edit_weight)
    actual = accumulate_visibility(avatar, video, edits, edit_weight)
    assert actual.dtype == torch.float64 and actual.shape == (len(avatar),)
    torch.testing.assert_close(actual, expected, rtol=0, atol=1e-9)


def test_without_edits_or_weight_v_is_the_video_mean(scene) -> None:
    avatar, video, edits, (video_brute, edit_brute) = scene
    video_mean = brute_force_combined(video_brute, [], 0.0)
    torch.testing.assert_close(accumulate_visibility(avatar, video), video_mean, rtol=0, atol=1e-9)
    torch.testing.assert_close(accumulate_visibility(avatar, video, (), 0.5), video_mean, rtol=0, atol=1e-9)
    torch.testing.assert_close(accumulate_visibility(avatar, video, edits, 0.0), video_mean, rtol=0, atol=1e-9)
    edit_mean = brute_force_combined(edit_brute, [], 0.0)
    torch.testing.assert_close(combine_visibility(video_mean, edit_mean, 1.0), edit_mean, rtol=0, atol=1e-12)
    assert combine_visibility(video_mean, None, 0.3) is video_mean


def test_float32_avatar_matches_brute_force() -> None:
    """The production precision: a float32 avatar and float32 poses against the float64 brute force."""
    avatar64 = rigid_avatar(48, seed=3)
    avatar32 = rigid_avatar(48, seed=3, dtype=torch.float32)
    video = random_views(3, seed=4, center=avatar64.rest_joints[0], dtype=torch.float32)
    edits = random_views(2, seed=5, center=avatar64.rest_joints[0], dtype=torch.float32)
    expected = brute_force_combined(brute_force_per_view(avatar64, video), brute_force_per_view(avatar64, edits), 0.2)
    actual = accumulate_visibility(avatar32, video, edits, 0.2)
    assert actual.dtype == torch.float64
    torch.testing.assert_close(actual, expected, rtol=1e-3, atol=1e-3 * float(expected.max()))


def test_world_transform_equals_moving_the_camera_the_other_way(scene) -> None:
    """Posing then applying a rigid world transform W, seen by camera C, is the plain pose seen by C @ W."""
    avatar, video, _, _ = scene
    view = video[0]
    world = torch.eye(4, dtype=torch.float64)
    world[:3, :3] = rotation_matrix(torch.tensor([0.2, -0.7, 0.4]))
    world[:3, 3] = torch.tensor([0.05, -0.1, 0.08], dtype=torch.float64)
    moved_camera = Camera(view.camera.K, view.camera.world_to_camera.double() @ world, WIDTH, HEIGHT)
    expected = brute_force_visibility(avatar, PoseFile(view.body_pose, view.transl, moved_camera))
    actual = gaussian_visibility(avatar, view, world)
    assert expected.sum() > 10.0
    torch.testing.assert_close(actual, expected, rtol=0, atol=1e-9)
    assert (actual - gaussian_visibility(avatar, view)).abs().max() > 1.0, "the transform must change what is seen"


def test_painted_visibility_matches_a_one_hot_colour_render(scene) -> None:
    """Each Gaussian's blend weight over weighted pixels, against the dense renderer drawing Gaussian i in
    colour channel i alone: channel i of pixel p is then T_i^p * alpha_i^p."""
    avatar, video, _, (video_brute, _) = scene
    view = video[0]
    weight = torch.rand(HEIGHT, WIDTH, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    weight[:, : WIDTH // 2] = 0.0
    means, quats = rigid_pose(avatar, view)
    p = avatar.params
    one_hot = torch.eye(len(avatar), dtype=torch.float64)
    image = rasterization_reference(
        means, quats, torch.exp(p["log_scales"].detach()), torch.sigmoid(p["opacity_logits"].detach()), one_hot,
        view.camera.to(dtype=torch.float64),
    )[0]  # fmt: skip
    expected = (image * weight[..., None]).sum(dim=(0, 1))
    actual = painted_visibility(avatar, view, weight)
    assert actual.dtype == torch.float64 and actual.shape == (len(avatar),)
    torch.testing.assert_close(actual, expected, rtol=0, atol=1e-9)
    assert int((expected > 0.01).sum()) >= 5, "the weighted half should show several Gaussians"
    assert bool(((expected == 0) & (video_brute[0] > 0.01)).any()), "some Gaussians show only on the unweighted half"
    torch.testing.assert_close(painted_visibility(avatar, view, torch.ones(HEIGHT, WIDTH)), video_brute[0], rtol=0, atol=1e-9)


def test_suggestion_weights_clip_below_the_mean() -> None:
    visibility = torch.tensor([0.0, 1.0, 5.0, 10.0, 4.0], dtype=torch.float64)
    mean = sum(visibility.tolist()) / 5
    expected = torch.tensor([min(v - mean, 0.0) for v in visibility.tolist()], dtype=torch.float64)
    torch.testing.assert_close(suggestion_weights(visibility), expected, rtol=0, atol=1e-15)
