"""The CPU rasterizer against the dense float64 reference: outputs, gradients, edge cases."""

from __future__ import annotations

import pytest
import torch

from avatarperfect_cli.render import Camera, look_at, rasterization
from avatarperfect_cli.render.cpu import rasterize_to_pixels
from avatarperfect_cli.render.projection import project_gaussians
from avatarperfect_cli.render.reference import rasterization_reference


def make_camera(width: int, height: int, dtype: torch.dtype = torch.float64) -> Camera:
    focal = 1.2 * max(width, height)
    K = torch.tensor([[focal, 0, width / 2 + 0.3], [0, focal * 1.05, height / 2 - 0.2], [0, 0, 1]], dtype=dtype)
    eye = torch.tensor([0.3, -0.2, -3.0], dtype=dtype)
    view = look_at(eye, torch.zeros(3, dtype=dtype), torch.tensor([0.0, -1.0, 0.0], dtype=dtype))
    return Camera(K, view, width, height)


def make_scene(seed: int, n: int, channels: int = 3, sh_degree: int | None = None, spread: float = 0.6):
    generator = torch.Generator().manual_seed(seed)

    def rand(*shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=generator, dtype=torch.float64)

    means = (rand(n, 3) - 0.5) * 2 * spread
    quats = torch.randn(n, 4, generator=generator, dtype=torch.float64)
    scales = 0.02 + 0.15 * rand(n, 3)
    opacities = 0.05 + 0.95 * rand(n)
    if sh_degree is None:
        colors = rand(n, channels)
    else:
        colors = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=generator, dtype=torch.float64) * 0.3
    return [means, quats, scales, opacities, colors]


def render_both(params, camera, sh_degree=None, background=None, dtype=torch.float64):
    fast = rasterization(
        *[p.to(dtype) for p in params], camera.to(dtype=dtype), sh_degree=sh_degree,
        background=None if background is None else background.to(dtype), render_depth=True,
    )  # fmt: skip
    ref = rasterization_reference(*params, camera, sh_degree=sh_degree, background=background)
    return fast, ref


def weighted_loss(image, alpha, depth, seed=7):
    generator = torch.Generator().manual_seed(seed)
    w_image = torch.randn(image.shape, generator=generator, dtype=torch.float64)
    w_alpha = torch.randn(alpha.shape, generator=generator, dtype=torch.float64)
    w_depth = torch.randn(depth.shape, generator=generator, dtype=torch.float64)
    return (image.double() * w_image).sum() + (alpha.double() * w_alpha).sum() + (depth.double() * w_depth).sum()


def relative_error(value: torch.Tensor, reference: torch.Tensor) -> float:
    return float((value.double() - reference).norm() / reference.norm().clamp_min(1e-30))


def assert_gradients_match(grads, expected_grads, tolerance):
    """Every parameter's gradient within `tolerance` relative error of a non-zero reference."""
    for name, grad, expected in zip(["means", "quats", "scales", "opacities", "colors"], grads, expected_grads):
        assert expected.abs().max() > 0, name
        assert relative_error(grad, expected) <= tolerance, name


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_forward_matches_reference(seed):
    camera = make_camera(37, 29)
    params = make_scene(seed, 60)
    background = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    fast, (image, alpha, depth, visibility) = render_both(params, camera, background=background)
    assert fast.image.shape == (29, 37, 3)
    assert alpha.max() > 0.9, "scene should cover some pixels densely"
    torch.testing.assert_close(fast.image, image, rtol=0, atol=1e-10)
    torch.testing.assert_close(fast.alpha, alpha, rtol=0, atol=1e-10)
    torch.testing.assert_close(fast.depth, depth, rtol=0, atol=1e-9)
    torch.testing.assert_close(fast.visibility, visibility, rtol=0, atol=1e-9)


def test_visibility_sums_to_alpha():
    camera = make_camera(40, 32)
    fast, _ = render_both(make_scene(5, 80), camera)
    torch.testing.assert_close(fast.visibility.sum(), fast.alpha.sum(), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("seed,sh_degree", [(0, None), (1, None), (2, 0), (3, 1), (4, 2), (5, 3)])
def test_gradients_match_reference_float64(seed, sh_degree):
    camera = make_camera(33, 27)
    params = [p.requires_grad_() for p in make_scene(seed, 40, sh_degree=sh_degree)]
    background = torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64)
    fast = rasterization(*params, camera, sh_degree=sh_degree, background=background, render_depth=True)
    fast_grads = torch.autograd.grad(weighted_loss(fast.image, fast.alpha, fast.depth), params)
    ref = rasterization_reference(*params, camera, sh_degree=sh_degree, background=background)
    ref_grads = torch.autograd.grad(weighted_loss(*ref[:3]), params)
    assert_gradients_match(fast_grads, ref_grads, 1e-6)


def test_gradients_of_a_masked_loss_match_reference():
    """A loss that sees only some pixels (an edit mask): the tiles it never sees send nothing back."""
    camera = make_camera(53, 41)
    params = [p.requires_grad_() for p in make_scene(6, 60)]
    mask = torch.zeros(41, 53, 1, dtype=torch.float64)
    mask[3:9, 30:45] = 1.0  # two 16-px tiles of the top row; every other tile has zero gradient
    fast = rasterization(*params, camera)
    fast_grads = torch.autograd.grad((fast.image * mask).sum(), params)
    ref_image = rasterization_reference(*params, camera)[0]
    ref_grads = torch.autograd.grad((ref_image * mask).sum(), params)
    assert_gradients_match(fast_grads, ref_grads, 1e-6)


def test_region_composites_only_its_pixels_with_the_full_images_values_and_gradients():
    camera = make_camera(53, 41)
    params = [p.requires_grad_() for p in make_scene(7, 60)]
    background = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    rows, cols = slice(5, 30), slice(18, 47)  # not aligned with the 16-px tiles
    full = rasterization(*params, camera, background=background)
    cropped = rasterization(*params, camera, background=background, region=(rows, cols))
    torch.testing.assert_close(cropped.image[rows, cols], full.image[rows, cols], rtol=0, atol=0)
    torch.testing.assert_close(cropped.alpha[rows, cols], full.alpha[rows, cols], rtol=0, atol=0)
    outside = torch.ones(41, 53, dtype=torch.bool)
    outside[rows, cols] = False
    assert full.alpha[outside].max() > 0.5, "the scene should cover pixels outside the region"
    assert (cropped.alpha[outside] == 0).all() and (cropped.image[outside] == background).all()
    weights = torch.randn(full.image.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    full_grads = torch.autograd.grad((full.image[rows, cols] * weights[rows, cols]).sum(), params)
    cropped_grads = torch.autograd.grad((cropped.image * weights).sum(), params)  # outside: a constant
    for name, grad, expected in zip(["means", "quats", "scales", "opacities", "colors"], cropped_grads, full_grads):
        assert expected.abs().max() > 0, name
        torch.testing.assert_close(grad, expected, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("seed", [0, 1])
def test_gradients_match_reference_float32(seed):
    camera = make_camera(33, 27)
    params = make_scene(seed, 40)
    params32 = [p.float().requires_grad_() for p in params]
    fast = rasterization(*params32, camera.to(dtype=torch.float32), render_depth=True)
    fast_grads = torch.autograd.grad(weighted_loss(fast.image, fast.alpha, fast.depth), params32)
    params64 = [p.requires_grad_() for p in params]
    ref_grads = torch.autograd.grad(weighted_loss(*rasterization_reference(*params64, camera)[:3]), params64)
    for name, grad, expected in zip(["means", "quats", "scales", "opacities", "colors"], fast_grads, ref_grads):
        assert relative_error(grad, expected) <= 1e-4, name


def test_gradcheck_compositing_kernel():
    generator = torch.Generator().manual_seed(11)
    n, width, height = 6, 9, 7
    means2d = (torch.rand(n, 2, generator=generator, dtype=torch.float64) * torch.tensor([width, height])).requires_grad_()
    axes = torch.rand(n, 2, generator=generator, dtype=torch.float64) * 3 + 1
    conics = torch.stack([1 / axes[:, 0] ** 2, 0.1 * torch.rand(n, generator=generator, dtype=torch.float64) / axes.prod(1), 1 / axes[:, 1] ** 2], dim=1)
    conics.requires_grad_()
    opacities = (0.3 + 0.6 * torch.rand(n, generator=generator, dtype=torch.float64)).requires_grad_()
    features = torch.rand(n, 2, generator=generator, dtype=torch.float64).requires_grad_()
    background = torch.rand(2, generator=generator, dtype=torch.float64).requires_grad_()
    extents = torch.full((n, 2), 20.0, dtype=torch.float64)
    depths = torch.rand(n, generator=generator, dtype=torch.float64)
    drawn = torch.ones(n, dtype=torch.bool)

    def image_and_alpha(m, c, o, f, b):
        image, alpha, _ = rasterize_to_pixels(m, c, o, f, b, extents, depths, drawn, width, height)
        return image, alpha

    assert torch.autograd.gradcheck(image_and_alpha, (means2d, conics, opacities, features, background), eps=1e-6, atol=1e-7)


def test_gradcheck_full_pipeline():
    camera = make_camera(12, 10)
    params = [p.requires_grad_() for p in make_scene(21, 5, sh_degree=1, spread=0.3)]

    def render(means, quats, scales, opacities, colors):
        out = rasterization(means, quats, scales, opacities, colors, camera, sh_degree=1, render_depth=True)
        return out.image, out.alpha, out.depth

    assert torch.autograd.gradcheck(render, tuple(params), eps=1e-7, atol=1e-6)


def test_early_termination_and_opacity_clamp():
    """A stack of opaque Gaussians: pixels stop before T <= 1e-4 and alpha saturates at 0.999."""
    K = torch.tensor([[20.0, 0, 8.5], [0, 20.0, 8.5], [0, 0, 1]], dtype=torch.float64)
    view = look_at(torch.tensor([0.0, 0, -3]), torch.zeros(3), torch.tensor([0.0, -1, 0])).double()
    camera = Camera(K, view, 17, 17)
    n = 8
    means = torch.zeros(n, 3, dtype=torch.float64)
    means[:, 2] = torch.linspace(-0.5, 0.5, n, dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).repeat(n, 1)
    scales = torch.full((n, 3), 0.4, dtype=torch.float64)
    opacities = torch.ones(n, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    params = [means, quats, scales, opacities, colors]
    fast, (image, alpha, depth, visibility) = render_both(params, camera)
    center_alpha = fast.alpha[8, 8]
    # Two Gaussians at alpha 0.999 leave T = 1e-6 <= 1e-4: only the first one composites.
    torch.testing.assert_close(center_alpha, torch.tensor(0.999, dtype=torch.float64))
    torch.testing.assert_close(fast.image, image, rtol=0, atol=1e-10)
    torch.testing.assert_close(fast.visibility, visibility, rtol=0, atol=1e-9)
    assert (fast.visibility[1:] < fast.visibility[0]).all()


def test_gaussians_behind_camera_and_across_border():
    camera = make_camera(20, 16)
    params = make_scene(3, 30, spread=1.2)
    params[0][:5, 2] = -4.0  # behind the camera (camera at z = -3 looking to +z)
    params[0][5:8, 0] = 1.1  # straddling the image border
    params = [p.requires_grad_() for p in params]
    fast = rasterization(*params, camera, render_depth=True)
    assert (fast.radii[:5] == 0).all()
    assert (fast.visibility[:5] == 0).all()
    grads = torch.autograd.grad(weighted_loss(fast.image, fast.alpha, fast.depth), params)
    assert all(torch.isfinite(g).all() for g in grads)
    assert (grads[0][:5] == 0).all()
    ref = rasterization_reference(*params, camera)
    torch.testing.assert_close(fast.image, ref[0], rtol=0, atol=1e-10)
    ref_grads = torch.autograd.grad(weighted_loss(*ref[:3]), params)
    for grad, expected in zip(grads, ref_grads):
        assert relative_error(grad, expected) <= 1e-6


def test_empty_scene_renders_background():
    camera = make_camera(8, 6)
    params = [p[:0] for p in make_scene(0, 1)]
    background = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    out = rasterization(*params, camera, background=background, render_depth=True)
    assert out.image.shape == (6, 8, 3)
    torch.testing.assert_close(out.image, background.expand(6, 8, 3))
    assert (out.alpha == 0).all() and (out.depth == 0).all() and out.visibility.shape == (0,)


def test_one_pixel_image():
    camera = make_camera(1, 1)
    params = [p.requires_grad_() for p in make_scene(4, 20, spread=0.2)]
    fast = rasterization(*params, camera, render_depth=True)
    ref = rasterization_reference(*params, camera)
    torch.testing.assert_close(fast.image, ref[0], rtol=0, atol=1e-10)
    assert fast.alpha.item() > 0.5
    grads = torch.autograd.grad(fast.image.sum() + fast.alpha.sum(), params)
    ref_grads = torch.autograd.grad(ref[0].sum() + ref[1].sum(), params)
    for grad, expected in zip(grads, ref_grads):
        assert relative_error(grad, expected) <= 1e-6


def test_single_channel_weight_image():
    """The one-channel image the pose suggestion renders: per-Gaussian weights as features."""
    camera = make_camera(24, 24)
    params = make_scene(8, 30)
    weights = torch.randn(30, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(1)).requires_grad_()
    out = rasterization(*params[:4], weights, camera)
    assert out.image.shape == (24, 24, 1)
    # d(sum of the image)/d(weight_i) is exactly Gaussian i's visibility.
    (grad,) = torch.autograd.grad(out.image.sum(), weights)
    torch.testing.assert_close(grad[:, 0], out.visibility, rtol=1e-10, atol=1e-12)


def test_radii_cover_every_touched_pixel():
    camera = make_camera(40, 40)
    params = make_scene(9, 25)
    projection = project_gaussians(*params[:4], camera)
    _, _, _, visibility = rasterization_reference(*params, camera)
    assert ((visibility > 0) <= projection.drawn).all()
