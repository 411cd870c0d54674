"""The numba SH colour kernels against the dense torch `eval_sh`, in float64, and gradcheck."""

from __future__ import annotations

import pytest
import torch

from avatarperfect_cli.gaussians import eval_sh
from avatarperfect_cli.gaussians.sh_kernels import eval_sh_cpu


def _inputs(degree: int, n: int = 60, extra_bands: int = 2, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    sh = torch.randn(n, (degree + 1) ** 2 + extra_bands, 3, dtype=torch.float64, generator=generator)
    dirs = torch.randn(n, 3, dtype=torch.float64, generator=generator) * 3.0
    return sh.requires_grad_(), dirs.requires_grad_()


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_colours_and_gradients_match_the_torch_evaluation(degree: int) -> None:
    """Values and both gradients equal the dense version's to float64 rounding, clamped colours
    included (about half of them with these coefficients), and the unused bands get zero gradient."""
    sh, dirs = _inputs(degree)
    expected = eval_sh(sh, dirs, degree)
    result = eval_sh_cpu(sh, dirs, degree)
    assert 0 < int((expected == 0).sum()) < expected.numel()
    torch.testing.assert_close(result, expected, rtol=0, atol=1e-13)
    upstream = torch.randn_like(expected)
    expected_grads = torch.autograd.grad(expected, (sh, dirs), upstream, allow_unused=True)
    grad_sh, grad_dirs = torch.autograd.grad(result, (sh, dirs), upstream)
    torch.testing.assert_close(grad_sh, expected_grads[0], rtol=0, atol=1e-13)
    expected_dirs = torch.zeros_like(dirs) if expected_grads[1] is None else expected_grads[1]
    torch.testing.assert_close(grad_dirs, expected_dirs, rtol=0, atol=1e-12)
    assert torch.equal(grad_sh[:, (degree + 1) ** 2 :], torch.zeros_like(grad_sh[:, (degree + 1) ** 2 :]))


@pytest.mark.parametrize("degree", [1, 3])
def test_gradcheck(degree: int) -> None:
    sh, dirs = _inputs(degree, n=12, seed=1)
    assert torch.autograd.gradcheck(lambda s, d: eval_sh_cpu(s, d, degree), (sh, dirs))


def test_float32_stays_float32_and_agrees() -> None:
    sh, dirs = _inputs(1, n=500, seed=2)
    result = eval_sh_cpu(sh.detach().float(), dirs.detach().float(), 1)
    assert result.dtype == torch.float32
    torch.testing.assert_close(result.double(), eval_sh(sh, dirs, 1).detach(), rtol=1e-5, atol=1e-5)


def test_bad_degree_or_too_few_coefficients_are_refused() -> None:
    sh, dirs = _inputs(1)
    with pytest.raises(ValueError, match="degree"):
        eval_sh_cpu(sh, dirs, 4)
    with pytest.raises(ValueError, match="coefficients"):
        eval_sh_cpu(sh[:, :3], dirs, 1)
