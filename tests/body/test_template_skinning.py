"""The template's skinning weights at canonical points: the grid k-nearest search against dense float64
distances, and the distance blend against its definition."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatarperfect_cli.body import BodyTemplate, load_body_template, load_described_template
from avatarperfect_cli.body.skeleton import forward_kinematics, skin_gaussians, skin_points
from avatarperfect_cli.body.template_skinning import (
    FALLOFF_FLOOR,
    GRID_CELL,
    bounded_pull_shares,
    largest_shift,
    nearest_vertices,
    reanchored_means,
    reanchored_quats,
    template_skin_weights,
)
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.rotations import quaternion_to_matrix


def random_template(count: int, seed: int = 0) -> BodyTemplate:
    generator = torch.Generator().manual_seed(seed)
    vertices = torch.rand(count, 3, generator=generator, dtype=torch.float64) * torch.tensor([0.6, 1.6, 0.3], dtype=torch.float64)
    raw = torch.rand(count, 24, generator=generator, dtype=torch.float64) ** 4
    return BodyTemplate(vertices, torch.zeros(0, 3, dtype=torch.int64), raw / raw.sum(1, keepdim=True), torch.zeros(24, 3))


def dense_nearest(points: np.ndarray, vertices: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    distances = torch.cdist(torch.from_numpy(points), torch.from_numpy(vertices), compute_mode="donot_use_mm_for_euclid_dist")
    values, indices = distances.topk(k, largest=False)
    return values.numpy(), indices.numpy()


@pytest.mark.parametrize("k", [1, 8, 40])
def test_grid_search_finds_the_dense_nearest_vertices(k: int):
    """Points near the vertices, far outside their box, and in empty space between clusters."""
    vertices = random_template(3000).vertices.numpy()
    vertices = np.concatenate([vertices, vertices[:200] + [2.0, 0.0, 0.0]])  # a far cluster: empty cells between
    rng = np.random.default_rng(1)
    points = np.concatenate([
        vertices[rng.choice(len(vertices), 500)] + rng.normal(0, 0.01, (500, 3)),  # near the surface
        rng.uniform(-4.0, 4.0, (300, 3)),  # mostly outside the grid
        vertices[:5],  # exactly on vertices
    ])  # fmt: skip
    distances, indices = nearest_vertices(points, vertices, k)
    expected_distances, expected_indices = dense_nearest(points, vertices, k)
    np.testing.assert_allclose(distances, expected_distances, rtol=0, atol=1e-12)
    assert (indices == expected_indices).mean() == 1.0
    assert (np.diff(distances, axis=1) >= 0).all()


def test_weights_are_the_distance_blend_of_the_nearest_vertices():
    template = random_template(2000, seed=3)
    points = template.vertices[:300] + torch.randn(300, 3, dtype=torch.float64) * 0.02
    distances, indices = dense_nearest(points.numpy(), template.vertices.numpy(), 8)
    blend = np.exp(-((distances / (distances[:, :1] + FALLOFF_FLOOR)) ** 2))
    expected = (blend[..., None] * template.weights.numpy()[indices]).sum(1) / blend.sum(1, keepdims=True)
    weights = template_skin_weights(template, points.float())
    assert weights.dtype == torch.float32 and weights.shape == (300, 24)
    np.testing.assert_allclose(weights.numpy(), expected, atol=1e-6)
    torch.testing.assert_close(weights.sum(1), torch.ones(300))


def test_an_isolated_vertex_gives_its_own_weights():
    """A point on a vertex whose neighbours lie many falloff floors away takes that vertex's weights."""
    template = random_template(50, seed=4)
    template.vertices *= 50 * GRID_CELL  # vertices about a metre apart, floor 5 mm
    weights = template_skin_weights(template, template.vertices.float())
    torch.testing.assert_close(weights, template.weights.float(), atol=1e-6, rtol=0)


def test_k_beyond_the_vertex_count_is_refused():
    with pytest.raises(ValueError, match="k must be"):
        template_skin_weights(random_template(5), torch.zeros(1, 3), k=6)


def test_described_template_is_the_one_train_initial_used():
    phenotype = {"height": 0.8, "weight": 0.4}
    described = load_described_template({"name": "anny", "phenotype": phenotype})
    torch.testing.assert_close(described.vertices, load_body_template("anny", phenotype=phenotype).vertices)
    with pytest.raises(AvatarPerfectError, match="does not name its body model"):
        load_described_template({})
    with pytest.raises(AvatarPerfectError, match="--smpl-model-dir"):
        load_described_template({"name": "smpl", "betas": [0.0] * 10})


def random_poses(count: int, seed: int) -> torch.Tensor:
    """(count, 24, 4, 4) joint transforms of random poses (up to 0.6 rad a joint) of a random skeleton."""
    generator = torch.Generator().manual_seed(seed)
    rest_joints = torch.rand(24, 3, generator=generator, dtype=torch.float64) * torch.tensor([0.6, 1.6, 0.3], dtype=torch.float64)
    body_pose = (torch.rand(count, 24, 3, generator=generator, dtype=torch.float64) - 0.5) * 1.2
    return forward_kinematics(body_pose, rest_joints, torch.zeros(count, 3, dtype=torch.float64))


def test_bounded_pull_moves_no_point_further_than_the_bound_in_any_pose():
    """Brute force: skin every point with the pulled weights in every pose and measure the shift; the
    points held back by the bound reach it exactly (skinning is linear in the weights)."""
    template = random_template(200, seed=5)
    generator = torch.Generator().manual_seed(6)
    means = template.vertices + torch.randn(200, 3, generator=generator, dtype=torch.float64) * 0.01
    learned = torch.softmax(torch.randn(200, 24, generator=generator, dtype=torch.float64) * 2, dim=1)
    target = template.weights.clone()
    target[:20] = learned[:20]  # these agree already: the whole way is free
    target[20:100] = torch.lerp(learned[20:100], target[20:100], 0.01)  # these differ little
    poses = random_poses(11, seed=7)
    max_shift, max_share = 0.01, 0.9
    shares = bounded_pull_shares(means, learned, target, poses, max_share, max_shift, poses_per_batch=4)
    assert shares.shape == (200,) and shares.dtype == torch.float32
    pulled = torch.lerp(learned, target, shares.double()[:, None])
    shift = (skin_points(means, pulled, poses) - skin_points(means, learned, poses)).norm(dim=-1).amax(dim=0)
    assert (shift <= max_shift * (1 + 1e-6)).all()
    held_back = shares < max_share
    assert 0 < held_back.sum() < 180  # the test exercises both cases
    torch.testing.assert_close(shift[held_back], torch.full_like(shift[held_back], max_shift), rtol=1e-6, atol=0)
    assert (shares[:20] == max_share).all() and (shares >= 0).all()


def random_gaussians(count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Canonical means (count, 3), quats of random norms (count, 4) and two sets of skinning weights that differ."""
    generator = torch.Generator().manual_seed(seed)
    means = torch.rand(count, 3, generator=generator, dtype=torch.float64) * torch.tensor([0.6, 1.6, 0.3], dtype=torch.float64)
    quats = torch.randn(count, 4, generator=generator, dtype=torch.float64)
    weights = torch.softmax(torch.randn(count, 24, generator=generator, dtype=torch.float64) * 2, dim=1)
    new_weights = torch.softmax(torch.randn(count, 24, generator=generator, dtype=torch.float64) * 2, dim=1)
    return means, quats, weights, new_weights


def rigidly_moved(body_pose: torch.Tensor, count: int, seed: int) -> torch.Tensor:
    """(count, 24, 4, 4) joint transforms of one body pose (24, 3) under `count` random global rotations and
    translations: a turntable."""
    generator = torch.Generator().manual_seed(seed)
    rest_joints = torch.rand(24, 3, generator=generator, dtype=torch.float64) * torch.tensor([0.6, 1.6, 0.3], dtype=torch.float64)
    poses = body_pose.expand(count, 24, 3).clone()
    poses[:, 0] = (torch.rand(count, 3, generator=generator, dtype=torch.float64) - 0.5) * 6.0
    return forward_kinematics(poses, rest_joints, torch.randn(count, 3, generator=generator, dtype=torch.float64))


def test_reanchoring_keeps_every_point_and_orientation_where_a_turntable_showed_it():
    """Poses that differ by a rigid motion of the whole body: skinned with the new weights, the re-anchored
    Gaussians land exactly where the old ones did, turned alike, in every pose; the quats keep their norms."""
    means, quats, weights, new_weights = random_gaussians(300, seed=8)
    body_pose = (torch.rand(24, 3, generator=torch.Generator().manual_seed(9), dtype=torch.float64) - 0.5) * 1.2
    poses = rigidly_moved(body_pose, 7, seed=10)
    new_means = reanchored_means(means, weights, new_weights, poses, points_per_batch=64)
    new_quats = reanchored_quats(means, quats, weights, new_weights, poses, poses=4)
    shift = largest_shift(means, weights, new_means, new_weights, poses)
    assert (new_means - means).norm(dim=1).median() > 0.01  # the weights differ: the canonical means must move
    torch.testing.assert_close(new_quats.norm(dim=1), quats.norm(dim=1), rtol=1e-12, atol=0)
    for pose in poses:
        old_means, old_quats = skin_gaussians(means, quats, weights, pose)
        moved_means, moved_quats = skin_gaussians(new_means, new_quats, new_weights, pose)
        torch.testing.assert_close(moved_means, old_means, rtol=0, atol=1e-9)
        torch.testing.assert_close(quaternion_to_matrix(moved_quats), quaternion_to_matrix(old_quats), rtol=0, atol=1e-9)
    assert float(shift.max()) < 1e-9


def test_reanchoring_for_the_same_weights_changes_nothing():
    means, quats, weights, _ = random_gaussians(100, seed=11)
    poses = random_poses(5, seed=12)
    new_means, new_quats = reanchored_means(means, weights, weights, poses), reanchored_quats(means, quats, weights, weights, poses)
    shift = largest_shift(means, weights, new_means, weights, poses)
    torch.testing.assert_close(new_means, means, rtol=0, atol=1e-12)
    torch.testing.assert_close(new_quats, quats * torch.sign(quats[:, :1] * new_quats[:, :1]), rtol=0, atol=1e-12)
    assert float(shift.max()) < 1e-12


def test_reanchored_means_are_the_least_squares_fit_over_poses_that_bend():
    """Poses that bend the body differently: no canonical mean keeps a point in place in all of them; the
    re-anchored one minimises the summed squared distance (its gradient vanishes), and the reported shift is
    the largest distance over the poses, by brute force."""
    means, _, weights, new_weights = random_gaussians(200, seed=13)
    poses = random_poses(9, seed=14)
    new_means = reanchored_means(means, weights, new_weights, poses, points_per_batch=50)
    shift = largest_shift(means, weights, new_means, new_weights, poses, poses_per_batch=2)
    target = skin_points(means, weights, poses)
    fitted = new_means.clone().requires_grad_(True)
    ((skin_points(fitted, new_weights, poses) - target) ** 2).sum().backward()
    assert float(fitted.grad.abs().max()) < 1e-9
    distances = (skin_points(new_means, new_weights, poses) - target).norm(dim=-1)
    torch.testing.assert_close(shift, distances.amax(dim=0), rtol=1e-12, atol=1e-15)
    assert float(distances.mean()) > 1e-4  # the poses do bend: no exact fit
