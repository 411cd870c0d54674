"""CUDA parity: gsplat through `rasterization(backend="cuda")` against the CPU kernels. Needs a GPU."""

from __future__ import annotations

import pytest
import torch

from avatarperfect_cli.render import rasterization

from .test_rasterization import make_camera, make_scene, relative_error, weighted_loss

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


@pytest.mark.parametrize("sh_degree", [None, 3])
def test_cuda_matches_cpu(sh_degree):
    pytest.importorskip("gsplat")
    camera = make_camera(64, 48, torch.float32)
    params = [p.float() for p in make_scene(0, 200, sh_degree=sh_degree)]
    background = torch.tensor([1.0, 1.0, 1.0])
    cpu_params = [p.clone().requires_grad_() for p in params]
    cuda_params = [p.cuda().requires_grad_() for p in params]
    cpu = rasterization(*cpu_params, camera, sh_degree=sh_degree, background=background, render_depth=True)
    cuda = rasterization(*cuda_params, camera, sh_degree=sh_degree, background=background.cuda(), render_depth=True)
    torch.testing.assert_close(cuda.image.cpu(), cpu.image, atol=2e-3, rtol=0)
    torch.testing.assert_close(cuda.alpha.cpu(), cpu.alpha, atol=2e-3, rtol=0)
    torch.testing.assert_close(cuda.visibility.cpu(), cpu.visibility, atol=1e-2, rtol=1e-3)
    cpu_grads = torch.autograd.grad(weighted_loss(cpu.image, cpu.alpha, cpu.depth), cpu_params)
    cuda_grads = torch.autograd.grad(weighted_loss(cuda.image.cpu(), cuda.alpha.cpu(), cuda.depth.cpu()), cuda_params)
    for cpu_grad, cuda_grad in zip(cpu_grads, cuda_grads):
        assert relative_error(cuda_grad.cpu(), cpu_grad.double()) < 1e-2


def test_screen_space_gradient_reaches_means2d_as_on_the_cpu():
    """Densification reads `means2d.grad` after backward; gsplat's centres are batched, so the backend hands
    out a leaf that a hook fills: it must hold the CPU's gradient (and nothing without a backward)."""
    pytest.importorskip("gsplat")
    camera = make_camera(64, 48, torch.float32)
    params = [p.float() for p in make_scene(1, 200)]
    grads = {}
    for device in ("cpu", "cuda"):
        leaves = [p.to(device).requires_grad_() for p in params]
        out = rasterization(*leaves, camera, background=torch.ones(3, device=device))
        out.means2d.retain_grad()
        assert out.means2d.shape == (200, 2) and out.means2d.grad is None
        weighted_loss(out.image.cpu(), out.alpha.cpu(), torch.zeros(48, 64)).backward()
        grads[device] = out.means2d.grad
        assert grads[device] is not None and grads[device].shape == (200, 2)
    assert grads["cpu"].abs().max() > 0
    assert relative_error(grads["cuda"].cpu(), grads["cpu"].double()) < 1e-2


def test_visibility_is_computed_only_when_read_and_without_the_background():
    pytest.importorskip("gsplat")
    camera = make_camera(64, 48, torch.float32)
    params = [p.float() for p in make_scene(2, 200)]
    cpu = rasterization(*params, camera, background=torch.tensor([0.3, 0.6, 0.9]))
    cuda = rasterization(*[p.cuda() for p in params], camera, background=torch.tensor([0.3, 0.6, 0.9], device="cuda"))
    assert callable(cuda._visibility)  # not computed yet
    torch.testing.assert_close(cuda.image.cpu(), cpu.image, atol=2e-3, rtol=0)
    torch.testing.assert_close(cuda.visibility.cpu(), cpu.visibility, atol=1e-2, rtol=1e-3)
    assert cuda.visibility is cuda.visibility  # computed once
