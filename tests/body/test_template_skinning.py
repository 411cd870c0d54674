"""The template's skinning weights at canonical points: the grid k-nearest search against dense float64
distances, and the distance blend against its definition."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatarperfect_cli.body import BodyTemplate, load_body_template, load_described_template
from avatarperfect_cli.body.template_skinning import FALLOFF_FLOOR, GRID_CELL, nearest_vertices, template_skin_weights
from avatarperfect_cli.errors import AvatarPerfectError


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
