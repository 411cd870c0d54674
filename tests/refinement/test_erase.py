"""Erase Center / Erase Splat selections against float64 brute force, and deleting Gaussians."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from avatarperfect_cli.avatar.model import PARAMETER_NAMES, Avatar
from avatarperfect_cli.body import load_body_template
from avatarperfect_cli.io.pose_json import PoseFile
from avatarperfect_cli.refinement.erase import (
    SPLAT_VISIBILITY,
    centres_in_region,
    delete_gaussians,
    select_in_region,
    splats_in_region,
)
from avatarperfect_cli.render import Camera, look_at
from tests.refinement.test_visibility import rigid_avatar, rigid_pose, rotation_matrix
from tests.render.test_max_weight import dense_weights

WIDTH, HEIGHT = 37, 29


def erase_view(avatar: Avatar, seed: int, dtype: torch.dtype = torch.float64) -> PoseFile:
    """A random global orientation and translation, seen from 1.5 m: with the avatar's wide spread some
    Gaussians fall behind the camera and many off the image."""
    generator = torch.Generator().manual_seed(seed)
    body_pose = torch.zeros(24, 3, dtype=torch.float64)
    body_pose[0] = torch.randn(3, generator=generator, dtype=torch.float64)
    transl = 0.1 * torch.randn(3, generator=generator, dtype=torch.float64)
    center = avatar.rest_joints[0].double()
    eye = center + torch.tensor([0.3, 0.2, 1.5], dtype=torch.float64)
    K = torch.tensor([[30.0, 0.0, 18.2], [0.0, 31.0, 14.7], [0.0, 0.0, 1.0]], dtype=torch.float64)
    camera = Camera(K, look_at(eye, center, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)), WIDTH, HEIGHT)
    return PoseFile(body_pose.to(dtype), transl.to(dtype), camera)


def random_region(seed: int) -> torch.Tensor:
    """(H, W) bool: a rectangle plus scattered pixels."""
    generator = torch.Generator().manual_seed(seed)
    region = torch.rand(HEIGHT, WIDTH, generator=generator) < 0.2
    region[5:20, 8:26] = True
    return region


def camera_points(avatar: Avatar, view: PoseFile) -> np.ndarray:
    """(N, 3) float64 posed means in the camera frame (independent rigid posing)."""
    means, _ = rigid_pose(avatar, view)
    view_matrix = view.camera.world_to_camera.double().numpy()
    return means.numpy() @ view_matrix[:3, :3].T + view_matrix[:3, 3]


def place_behind_camera(avatar: Avatar, view: PoseFile, count: int) -> None:
    """Move the first `count` Gaussians behind the camera, 0.3-1 m back, where the mirrored pinhole projection
    (x/z, y/z with z < 0) lands in the middle of the image: a sign slip would select them."""
    generator = torch.Generator().manual_seed(count)
    depth = 0.3 + 0.7 * torch.rand(count, generator=generator, dtype=torch.float64)
    offsets = 0.2 * (torch.rand(count, 2, generator=generator, dtype=torch.float64) - 0.5)
    local = torch.cat([offsets * depth[:, None], -depth[:, None]], dim=1)
    view_matrix = view.camera.world_to_camera.double()
    world = (local - view_matrix[:3, 3]) @ view_matrix[:3, :3]
    rotation = rotation_matrix(view.body_pose[0])
    j0 = avatar.rest_joints[0].double()
    canonical = (world - j0 - view.transl.double()) @ rotation + j0  # the inverse of the rigid pose
    with torch.no_grad():
        avatar.params["means"][:count] = canonical.to(avatar.params["means"].dtype)


def brute_force_centres(avatar: Avatar, view: PoseFile, region: torch.Tensor) -> tuple[torch.Tensor, np.ndarray]:
    """(N,) bool selection by projecting every centre on its own, and the (N, 2) pixel positions (NaN behind)."""
    K = view.camera.K.double().numpy()
    selected, pixels = [], []
    for local in camera_points(avatar, view):
        if local[2] <= 0.0:
            selected.append(False)
            pixels.append((math.nan, math.nan))
            continue
        u, v, _ = K @ (local / local[2])
        column, row = math.floor(u), math.floor(v)
        selected.append(0 <= column < WIDTH and 0 <= row < HEIGHT and bool(region[row, column]))
        pixels.append((u, v))
    return torch.tensor(selected), np.array(pixels)


def brute_force_splats(avatar: Avatar, view: PoseFile, region: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N,) bool max over region pixels of the dense T * alpha > 0.01, and those maxima."""
    means, quats = rigid_pose(avatar, view)
    scales = torch.exp(avatar.params["log_scales"].detach().double())
    opacities = torch.sigmoid(avatar.params["opacity_logits"].detach().double())
    weights = dense_weights([means, quats, scales, opacities], view.camera.to(dtype=torch.float64))
    maxima = torch.where(region[..., None], weights, 0.0).amax(dim=(0, 1))
    return maxima > SPLAT_VISIBILITY, maxima


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_centres_in_region_match_per_gaussian_projection(seed: int) -> None:
    avatar = rigid_avatar(300, seed=10 + seed, spread=2.0)
    view = erase_view(avatar, seed)
    place_behind_camera(avatar, view, 10)
    region = random_region(seed)
    expected, pixels = brute_force_centres(avatar, view, region)
    depth = camera_points(avatar, view)[:, 2]
    assert not ((depth > 0) & (depth < 1e-3)).any(), "keep clear of the in-front threshold's exact value"
    behind = depth <= 0
    # a centre behind the camera whose mirrored projection lands on a selected pixel must not be selected
    K = view.camera.K.double().numpy()
    mirrored = camera_points(avatar, view)[behind] @ K.T
    mirrored = torch.from_numpy(np.floor(mirrored[:, :2] / mirrored[:, 2:])).long()
    lands = (mirrored[:, 0] >= 0) & (mirrored[:, 0] < WIDTH) & (mirrored[:, 1] >= 0) & (mirrored[:, 1] < HEIGHT)
    assert region[mirrored[lands, 1], mirrored[lands, 0]].any(), "exercise the behind-camera case"
    off_image = ~behind & ((pixels[:, 0] < 0) | (pixels[:, 0] >= WIDTH) | (pixels[:, 1] < 0) | (pixels[:, 1] >= HEIGHT))
    assert off_image.sum() >= 10 and 10 <= expected.sum() < len(avatar) - 10

    actual = centres_in_region(avatar, view, region)
    assert actual.dtype == torch.bool and actual.shape == (len(avatar),)
    assert torch.equal(actual, expected)


def test_centres_in_region_float32_avatar() -> None:
    """The production precision: agreement with the float64 brute force except for centres within
    1e-4 px of a pixel edge, where float32 rounding may pick the neighbour."""
    avatar64 = rigid_avatar(300, seed=20, spread=2.0)
    avatar32 = rigid_avatar(300, seed=20, spread=2.0, dtype=torch.float32)
    view = erase_view(avatar64, 5, dtype=torch.float32)
    region = random_region(5)
    expected, pixels = brute_force_centres(avatar64, view, region)
    actual = centres_in_region(avatar32, view, region)
    distance_to_edge = np.abs(pixels - np.round(pixels)).min(axis=1)
    near_edge = torch.from_numpy(np.nan_to_num(distance_to_edge, nan=1.0) < 1e-4)
    assert expected.sum() >= 10
    assert torch.equal(actual[~near_edge], expected[~near_edge])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_splats_in_region_match_dense_weights(seed: int) -> None:
    avatar = rigid_avatar(150, seed=30 + seed, spread=1.0)
    view = erase_view(avatar, seed)
    region = random_region(seed)
    expected, maxima = brute_force_splats(avatar, view, region)
    assert 5 <= expected.sum() < len(avatar) - 5
    assert ((maxima > 0) & (maxima <= SPLAT_VISIBILITY)).any(), "some Gaussians should reach the region faintly"
    assert not ((maxima - SPLAT_VISIBILITY).abs() < 1e-9).any(), "keep clear of the threshold's exact value"
    actual = splats_in_region(avatar, view, region)
    assert actual.dtype == torch.bool and actual.shape == (len(avatar),)
    assert torch.equal(actual, expected)
    assert torch.equal(splats_in_region(avatar, view, region, threshold=0.2), maxima > 0.2)


def test_select_in_region_dispatches_by_mode() -> None:
    avatar = rigid_avatar(150, seed=40, spread=1.0)
    view = erase_view(avatar, 3)
    region = random_region(3)
    centres = select_in_region(avatar, view, region, "center")
    splats = select_in_region(avatar, view, region, "splat")
    assert torch.equal(centres, brute_force_centres(avatar, view, region)[0])
    assert torch.equal(splats, brute_force_splats(avatar, view, region)[0])
    assert not torch.equal(centres, splats)
    with pytest.raises(ValueError, match="erase mode"):
        select_in_region(avatar, view, region, "lasso")


def test_delete_gaussians_keeps_the_others_exactly() -> None:
    template = load_body_template("anny")
    avatar = Avatar.from_template(template, sh_degree=1, body_model={"name": "anny"})
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for name in PARAMETER_NAMES:  # distinct values everywhere, so a shifted index cannot pass
            avatar.params[name].add_(0.01 * torch.randn(avatar.params[name].shape, generator=generator))
    avatar.active_sh_degree = 1
    before = {name: avatar.params[name].detach().clone() for name in PARAMETER_NAMES}
    delete = torch.rand(len(avatar), generator=generator) < 0.3
    kept_indices = [i for i in range(len(avatar)) if not delete[i]]

    result = delete_gaussians(avatar, delete)

    assert len(result) == len(kept_indices)
    for name in PARAMETER_NAMES:
        assert torch.equal(result.params[name].detach(), before[name][kept_indices]), name
        assert torch.equal(avatar.params[name].detach(), before[name]), f"the input's {name} changed"
        assert isinstance(result.params[name], torch.nn.Parameter)
    assert torch.equal(result.rest_joints, avatar.rest_joints)
    assert (result.sh_degree, result.active_sh_degree, result.body_model) == (1, 1, {"name": "anny"})
    assert len(delete_gaussians(avatar, torch.zeros(len(avatar), dtype=torch.bool))) == len(avatar)
    assert len(delete_gaussians(avatar, torch.ones(len(avatar), dtype=torch.bool))) == 0
