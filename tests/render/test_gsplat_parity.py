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
    cuda_grads = torch.autograd.grad(weighted_loss(cuda.image, cuda.alpha, cuda.depth), cuda_params)
    for cpu_grad, cuda_grad in zip(cpu_grads, cuda_grads):
        assert relative_error(cuda_grad.cpu(), cpu_grad.double()) < 1e-2
