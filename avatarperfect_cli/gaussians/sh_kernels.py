"""numba kernels of the SH colour evaluation (degrees 0 to 3) and its backward, for the CPU renderer.

The same function as `sh.eval_sh` (the dense torch version, which stays the reference and the path for
other devices): colour = max(0, sum_k Y_k(d / |d|) sh_k + 0.5). One `prange` over the Gaussians; on the
512² refine step the torch version's forward and backward took about 6 ms of a 62 ms step.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from numba import njit, prange

from avatarperfect_cli.gaussians.sh import SH_C0, SH_C1, SH_C2, SH_C3

MAX_DEGREE = 3
# The Gaussians are cut into this many chunks, each with its own scratch arrays (an allocation per
# Gaussian would cost more than its arithmetic).
_CHUNKS = 64


@njit(cache=True, inline="always")
def _basis(x, y, z, degree, out):
    """out[:(degree + 1)^2] = the SH basis at the unit direction (x, y, z)."""
    out[0] = SH_C0
    if degree >= 1:
        out[1], out[2], out[3] = -SH_C1 * y, SH_C1 * z, -SH_C1 * x
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out[4] = SH_C2[0] * x * y
        out[5] = SH_C2[1] * y * z
        out[6] = SH_C2[2] * (2.0 * zz - xx - yy)
        out[7] = SH_C2[3] * x * z
        out[8] = SH_C2[4] * (xx - yy)
        if degree >= 3:
            out[9] = SH_C3[0] * y * (3.0 * xx - yy)
            out[10] = SH_C3[1] * x * y * z
            out[11] = SH_C3[2] * y * (4.0 * zz - xx - yy)
            out[12] = SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
            out[13] = SH_C3[4] * x * (4.0 * zz - xx - yy)
            out[14] = SH_C3[5] * z * (xx - yy)
            out[15] = SH_C3[6] * x * (xx - 3.0 * yy)


@njit(cache=True, inline="always")
def _basis_gradient(x, y, z, degree, g, out):
    """out = (d/dx, d/dy, d/dz) of sum_k g[k] Y_k at the direction (x, y, z) (Y_k as polynomials)."""
    gx = -SH_C1 * g[3] if degree >= 1 else 0.0
    gy = -SH_C1 * g[1] if degree >= 1 else 0.0
    gz = SH_C1 * g[2] if degree >= 1 else 0.0
    if degree >= 2:
        gx += SH_C2[0] * y * g[4] - 2.0 * SH_C2[2] * x * g[6] + SH_C2[3] * z * g[7] + 2.0 * SH_C2[4] * x * g[8]
        gy += SH_C2[0] * x * g[4] + SH_C2[1] * z * g[5] - 2.0 * SH_C2[2] * y * g[6] - 2.0 * SH_C2[4] * y * g[8]
        gz += SH_C2[1] * y * g[5] + 4.0 * SH_C2[2] * z * g[6] + SH_C2[3] * x * g[7]
        if degree >= 3:
            xx, yy, zz = x * x, y * y, z * z
            gx += (
                6.0 * SH_C3[0] * x * y * g[9] + SH_C3[1] * y * z * g[10] - 2.0 * SH_C3[2] * x * y * g[11]
                - 6.0 * SH_C3[3] * x * z * g[12] + SH_C3[4] * (4.0 * zz - 3.0 * xx - yy) * g[13]
                + 2.0 * SH_C3[5] * x * z * g[14] + 3.0 * SH_C3[6] * (xx - yy) * g[15]
            )  # fmt: skip
            gy += (
                3.0 * SH_C3[0] * (xx - yy) * g[9] + SH_C3[1] * x * z * g[10] + SH_C3[2] * (4.0 * zz - xx - 3.0 * yy) * g[11]
                - 6.0 * SH_C3[3] * y * z * g[12] - 2.0 * SH_C3[4] * x * y * g[13] - 2.0 * SH_C3[5] * y * z * g[14]
                - 6.0 * SH_C3[6] * x * y * g[15]
            )  # fmt: skip
            gz += (
                SH_C3[1] * x * y * g[10] + 8.0 * SH_C3[2] * y * z * g[11] + SH_C3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy) * g[12]
                + 8.0 * SH_C3[4] * x * z * g[13] + SH_C3[5] * (xx - yy) * g[14]
            )  # fmt: skip
    out[0], out[1], out[2] = gx, gy, gz


@njit(cache=True, parallel=True)
def sh_forward(sh, dirs, degree):
    """sh (N, K, C), dirs (N, 3) any length, K >= (degree + 1)^2 -> colours (N, C), clamped at 0."""
    n, channels = sh.shape[0], sh.shape[2]
    bases = (degree + 1) ** 2
    colors = np.empty((n, channels), dtype=sh.dtype)
    for chunk in prange(_CHUNKS):
        basis = np.empty(16, dtype=np.float64)
        for i in range(chunk * n // _CHUNKS, (chunk + 1) * n // _CHUNKS):
            norm = math.sqrt(dirs[i, 0] ** 2 + dirs[i, 1] ** 2 + dirs[i, 2] ** 2)
            inv = 1.0 / max(norm, 1e-12)  # as torch.nn.functional.normalize
            _basis(dirs[i, 0] * inv, dirs[i, 1] * inv, dirs[i, 2] * inv, degree, basis)
            for c in range(channels):
                value = 0.5
                for k in range(bases):
                    value += basis[k] * sh[i, k, c]
                colors[i, c] = max(value, 0.0)
    return colors


@njit(cache=True, parallel=True)
def sh_backward(sh, dirs, degree, colors, grad_colors):
    """Gradients of a loss through `sh_forward`: (grad_sh (N, K, C), grad_dirs (N, 3)); rows of sh past
    the degree's bases get zero, as do clamped colours."""
    n, channels = sh.shape[0], sh.shape[2]
    bases = (degree + 1) ** 2
    grad_sh = np.zeros(sh.shape, dtype=sh.dtype)
    grad_dirs = np.zeros((n, 3), dtype=dirs.dtype)
    for chunk in prange(_CHUNKS):
        basis = np.empty(16, dtype=np.float64)
        grad_basis = np.empty(16, dtype=np.float64)
        unit_gradient = np.empty(3, dtype=np.float64)
        for i in range(chunk * n // _CHUNKS, (chunk + 1) * n // _CHUNKS):
            grad_basis[:] = 0.0
            norm = math.sqrt(dirs[i, 0] ** 2 + dirs[i, 1] ** 2 + dirs[i, 2] ** 2)
            inv = 1.0 / max(norm, 1e-12)
            x, y, z = dirs[i, 0] * inv, dirs[i, 1] * inv, dirs[i, 2] * inv
            _basis(x, y, z, degree, basis)
            for c in range(channels):
                if colors[i, c] <= 0.0:
                    continue  # clamped: no gradient
                g = grad_colors[i, c]
                for k in range(bases):
                    grad_sh[i, k, c] = basis[k] * g
                    grad_basis[k] += sh[i, k, c] * g
            if degree == 0 or norm < 1e-12:
                continue
            _basis_gradient(x, y, z, degree, grad_basis, unit_gradient)
            # through u = d / |d|: (g - u (u . g)) / |d|
            along = x * unit_gradient[0] + y * unit_gradient[1] + z * unit_gradient[2]
            grad_dirs[i, 0] = (unit_gradient[0] - x * along) * inv
            grad_dirs[i, 1] = (unit_gradient[1] - y * along) * inv
            grad_dirs[i, 2] = (unit_gradient[2] - z * along) * inv
    return grad_sh, grad_dirs


class _EvalSH(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, sh: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:  # type: ignore[override]
        arrays = (np.ascontiguousarray(sh.detach().numpy()), np.ascontiguousarray(dirs.detach().numpy()))
        colors = sh_forward(*arrays, degree)
        ctx.saved = (*arrays, degree, colors)
        return torch.from_numpy(colors)

    @staticmethod
    def backward(ctx: Any, grad_colors: torch.Tensor) -> tuple[torch.Tensor | None, ...]:  # type: ignore[override]
        grad_sh, grad_dirs = sh_backward(*ctx.saved, np.ascontiguousarray(grad_colors.detach().numpy()))
        return torch.from_numpy(grad_sh), torch.from_numpy(grad_dirs), None


def eval_sh_cpu(sh: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """`sh.eval_sh` on CPU tensors through the numba kernels: sh (N, K, C) with K >= (degree + 1)^2,
    dirs (N, 3) camera centre -> Gaussian, any length; returns (N, C) colours, clamped at 0."""
    if not 0 <= degree <= MAX_DEGREE:
        raise ValueError(f"SH degree must be in [0, {MAX_DEGREE}], got {degree}")
    if sh.shape[1] < (degree + 1) ** 2:
        raise ValueError(f"degree {degree} needs {(degree + 1) ** 2} SH coefficients, got {sh.shape[1]}")
    return _EvalSH.apply(sh, dirs, degree)
