"""`max_weight_in_region` (the Erase Splat kernel) against dense per-pixel blending weights from the reference."""

from __future__ import annotations

import pytest
import torch

from avatarperfect_cli.render import Camera, look_at
from avatarperfect_cli.render.cpu import max_weight_in_region
from avatarperfect_cli.render.projection import project_gaussians
from avatarperfect_cli.render.reference import composite_dense, project_dense


def random_scene(seed: int, n: int, spread: float) -> tuple[list[torch.Tensor], Camera]:
    """n random float64 Gaussians in a cube of half-side `spread` m and a 37 x 29 px camera 3 m away
    (3 x 2 tiles of 16 px, the last ones partial); a large spread puts some behind the camera."""
    generator = torch.Generator().manual_seed(seed)

    def rand(*shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=generator, dtype=torch.float64)

    means = (rand(n, 3) - 0.5) * 2 * spread
    quats = torch.randn(n, 4, generator=generator, dtype=torch.float64)
    scales = 0.02 + 0.15 * rand(n, 3)
    opacities = 0.05 + 0.95 * rand(n)
    K = torch.tensor([[40.0, 0, 18.8], [0, 42.0, 14.3], [0, 0, 1]], dtype=torch.float64)
    view = look_at(torch.tensor([0.3, -0.2, -3.0]), torch.zeros(3), torch.tensor([0.0, -1.0, 0.0])).double()
    return [means, quats, scales, opacities], Camera(K, view, 37, 29)


def dense_weights(params: list[torch.Tensor], camera: Camera) -> torch.Tensor:
    """(H, W, N) float64 blending weight T * alpha of every Gaussian at every pixel (dense reference)."""
    means, quats, scales, opacities = params
    means2d, precision, depths, valid = project_dense(means, quats, scales, camera, 0.01, 1e10, 0.3)
    ys, xs = torch.meshgrid(torch.arange(camera.height), torch.arange(camera.width), indexing="ij")
    pixels = torch.stack([xs, ys], dim=-1).reshape(-1, 2).double() + 0.5
    order = torch.sort(depths, stable=True).indices
    features = torch.zeros(len(means), 1, dtype=torch.float64)
    _, _, in_order = composite_dense(pixels, means2d, precision, opacities, features, features[0], order, valid)
    weights = torch.zeros_like(in_order)
    weights[:, order] = in_order
    return weights.reshape(camera.height, camera.width, -1)


def kernel_weights(
    params: list[torch.Tensor], camera: Camera, region: torch.Tensor, dtype: torch.dtype
) -> torch.Tensor:
    """(N,) `max_weight_in_region` of the Gaussians `params` projected by `camera`, in `dtype`."""
    means, quats, scales, opacities = (param.to(dtype) for param in params)
    projection = project_gaussians(means, quats, scales, opacities, camera.to(dtype=dtype))
    return max_weight_in_region(
        projection.means2d, projection.conics, opacities, projection.extents, projection.depths, projection.drawn, region
    )


def regions(seed: int, height: int, width: int) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    one_tile = torch.zeros(height, width, dtype=torch.bool)
    one_tile[18:25, 3:12] = True  # inside the second row's first tile only
    single = torch.zeros(height, width, dtype=torch.bool)
    single[14, 18] = True
    return {
        "scattered": torch.rand(height, width, generator=generator) < 0.3,
        "one tile": one_tile,
        "one pixel": single,
        "everything": torch.ones(height, width, dtype=torch.bool),
        "nothing": torch.zeros(height, width, dtype=torch.bool),
    }


@pytest.mark.parametrize("seed,n,spread", [(0, 60, 0.6), (1, 120, 0.8), (2, 80, 3.5)])
def test_max_weight_in_region_matches_dense_float64(seed: int, n: int, spread: float) -> None:
    params, camera = random_scene(seed, n, spread)
    dense = dense_weights(params, camera)
    assert dense.sum(dim=-1).max() > 0.9, "the scene should cover some pixels densely"
    depths = params[0] @ camera.world_to_camera[2, :3] + camera.world_to_camera[2, 3]
    assert spread < 3.0 or (depths < 0).any(), "the wide scene should hold Gaussians behind the camera"
    for name, region in regions(seed, camera.height, camera.width).items():
        expected = torch.where(region[..., None], dense, 0.0).amax(dim=(0, 1))
        actual = kernel_weights(params, camera, region, torch.float64)
        assert actual.dtype == torch.float64 and actual.shape == (n,)
        torch.testing.assert_close(actual, expected, rtol=0, atol=1e-10, msg=lambda m: f"region {name}: {m}")
        if name == "one tile":
            assert (expected > 0.01).any() and (expected == 0).any(), "a small region should select some, not all"


def test_max_weight_in_region_float32() -> None:
    params, camera = random_scene(3, 90, 0.7)
    region = regions(3, camera.height, camera.width)["scattered"]
    expected = torch.where(region[..., None], dense_weights(params, camera), 0.0).amax(dim=(0, 1))
    actual = kernel_weights(params, camera, region, torch.float32)
    assert actual.dtype == torch.float32
    torch.testing.assert_close(actual.double(), expected, rtol=0, atol=1e-5)


def test_max_weight_follows_occlusion_and_termination() -> None:
    """Opaque Gaussians stacked on the optical axis: the nearest takes 0.999, the second nothing
    (T would fall to 1e-6 <= 1e-4), and a Gaussian behind the camera never counts."""
    K = torch.tensor([[20.0, 0, 8.5], [0, 20.0, 8.5], [0, 0, 1]], dtype=torch.float64)
    camera = Camera(K, look_at(torch.tensor([0.0, 0, -3]), torch.zeros(3), torch.tensor([0.0, -1, 0])).double(), 17, 17)
    means = torch.tensor([[0.0, 0, 0.5], [0, 0, -0.5], [0, 0, -4.0]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).repeat(3, 1)
    scales = torch.full((3, 3), 0.4, dtype=torch.float64)
    opacities = torch.ones(3, dtype=torch.float64)
    centre = torch.zeros(17, 17, dtype=torch.bool)
    centre[8, 8] = True
    weights = kernel_weights([means, quats, scales, opacities], camera, centre, torch.float64)
    torch.testing.assert_close(weights, torch.tensor([0.0, 0.999, 0.0], dtype=torch.float64), rtol=0, atol=1e-12)
