"""Spherical harmonics: an orthonormal real basis, and the colour helpers invert each other."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from avatarperfect_cli.gaussians import eval_sh, rgb_to_sh, sh_to_rgb
from avatarperfect_cli.gaussians.sh import sh_basis


def sphere_quadrature(n_theta: int = 64, n_phi: int = 128) -> tuple[torch.Tensor, torch.Tensor]:
    """Gauss-Legendre in cos(theta) x uniform in phi: exact for the degree-6 products tested here."""
    x, w = np.polynomial.legendre.leggauss(n_theta)
    cos_theta = torch.tensor(x, dtype=torch.float64)
    phi = torch.arange(n_phi, dtype=torch.float64) * 2 * math.pi / n_phi
    c, p = torch.meshgrid(cos_theta, phi, indexing="ij")
    s = torch.sqrt(1 - c**2)
    nodes = torch.stack([s * torch.cos(p), s * torch.sin(p), c], dim=-1).reshape(-1, 3)
    weights = (torch.tensor(w, dtype=torch.float64)[:, None] * (2 * math.pi / n_phi)).expand(n_theta, n_phi).reshape(-1)
    return nodes, weights


def test_basis_is_orthonormal_on_the_sphere():
    dirs, weights = sphere_quadrature()
    basis = sh_basis(dirs, 3)  # (P, 16)
    gram = basis.T @ (basis * weights[:, None])
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=1e-10, rtol=0)


def test_degree_one_follows_the_3dgs_sign_convention():
    # 3DGS / gsplat: the degree-1 basis is C1 * (-y, z, -x).
    dirs = torch.eye(3, dtype=torch.float64)
    c1 = math.sqrt(3 / (4 * math.pi))
    expected = torch.tensor([[0, 0, -c1], [-c1, 0, 0], [0, c1, 0]], dtype=torch.float64)
    torch.testing.assert_close(sh_basis(dirs, 1)[:, 1:], expected)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_eval_sh_ignores_higher_bands_and_direction_length(degree):
    generator = torch.Generator().manual_seed(degree)
    sh = torch.randn(5, 16, 3, generator=generator, dtype=torch.float64) * 0.2
    dirs = torch.randn(5, 3, generator=generator, dtype=torch.float64)
    colors = eval_sh(sh, dirs, degree)
    truncated = sh[:, : (degree + 1) ** 2]
    torch.testing.assert_close(colors, eval_sh(truncated, 7.0 * dirs, degree))
    manual = torch.clamp_min(torch.einsum("nk,nkc->nc", sh_basis(dirs / dirs.norm(dim=-1, keepdim=True), degree), truncated) + 0.5, 0)
    torch.testing.assert_close(colors, manual)


def test_rgb_round_trip_and_dc_only_render():
    rgb = torch.rand(10, 3, dtype=torch.float64)
    torch.testing.assert_close(sh_to_rgb(rgb_to_sh(rgb)), rgb)
    sh = rgb_to_sh(rgb)[:, None, :]
    torch.testing.assert_close(eval_sh(sh, torch.randn(10, 3, dtype=torch.float64), 0), rgb)
