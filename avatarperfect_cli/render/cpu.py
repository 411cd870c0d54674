"""Differentiable compositing of projected Gaussians on the CPU, through the numba kernels."""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import torch

from avatarperfect_cli.render import cpu_kernels as kernels

TILE_SIZE = 16


def _array(tensor: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(tensor.detach().cpu().numpy())


class _RasterizeToPixels(torch.autograd.Function):
    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        means2d: torch.Tensor,
        conics: torch.Tensor,
        opacities: torch.Tensor,
        features: torch.Tensor,
        background: torch.Tensor,
        extents: torch.Tensor,
        depths: torch.Tensor,
        drawn: torch.Tensor,
        width: int,
        height: int,
        region: np.ndarray,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        means2d_np, conics_np, opacities_np, drawn_np = (_array(t) for t in (means2d, conics, opacities, drawn))
        spans = kernels.gaussian_spans(conics_np, opacities_np, drawn_np)
        depth_array = _array(depths)
        depth_keys = depth_array.view(np.uint32 if depth_array.itemsize == 4 else np.uint64)
        n_threads = numba.get_num_threads()
        offsets, tile_gaussians = kernels.bin_gaussians(
            means2d_np, _array(extents), depth_keys, 8 * depth_array.itemsize, drawn_np,
            width, height, TILE_SIZE, region, n_threads,
        )  # fmt: skip
        packed = kernels.pack_intersections(means2d_np, conics_np, opacities_np, _array(features), spans, tile_gaussians, n_threads)
        layout = (_array(background), offsets, kernels.tile_schedule(offsets), width, height, TILE_SIZE, n_threads)
        image, transmittance, last, weights = kernels.rasterize_forward(packed, *layout, region)
        visibility = kernels.sum_per_gaussian(weights[:, None], tile_gaussians, means2d.shape[0])[:, 0]
        ctx.packed, ctx.layout, ctx.tile_gaussians, ctx.n_gaussians = packed, layout, tile_gaussians, means2d.shape[0]
        ctx.transmittance = transmittance
        ctx.last = last
        visibility_t = torch.from_numpy(visibility)
        ctx.mark_non_differentiable(visibility_t)
        return torch.from_numpy(image), torch.from_numpy(1.0 - transmittance), visibility_t

    @staticmethod
    def backward(  # type: ignore[override]
        ctx: Any, grad_image: torch.Tensor, grad_alpha: torch.Tensor, _grad_visibility: torch.Tensor
    ) -> tuple[torch.Tensor | None, ...]:
        records = kernels.rasterize_backward(
            ctx.packed, *ctx.layout, ctx.transmittance, ctx.last, _array(grad_image), _array(grad_alpha)
        )
        grads = torch.from_numpy(kernels.sum_per_gaussian(records, ctx.tile_gaussians, ctx.n_gaussians))
        grad_background = None
        if ctx.needs_input_grad[4]:
            grad_background = torch.from_numpy(
                np.einsum("hw,hwc->c", ctx.transmittance, _array(grad_image)).astype(ctx.packed.dtype)
            )
        return (
            grads[:, kernels.G_MEAN_X : kernels.G_MEAN_Y + 1],
            grads[:, kernels.G_CONIC_A : kernels.G_CONIC_C + 1],
            grads[:, kernels.G_OPACITY],
            grads[:, kernels.G_FEATURES :],
            grad_background,
            None,
            None,
            None,
            None,
            None,
            None,
        )


def rasterize_to_pixels(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    background: torch.Tensor,
    extents: torch.Tensor,
    depths: torch.Tensor,
    drawn: torch.Tensor,
    width: int,
    height: int,
    region: tuple[slice, slice] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Composite projected Gaussians front to back (gsplat conventions), on the CPU.

    means2d (N, 2) pixels; conics (N, 3) 1/pixel^2; opacities (N,); features (N, C) any channels;
    background (C,); extents (N, 2) pixels and depths (N,) metres for binning; drawn (N,) bool;
    region: (rows, cols) slices of the pixels to composite (default all); the others are background
    with alpha 0 and pass no gradient.
    Returns image (H, W, C), alpha (H, W) and visibility (N,) = sum over the composited pixels of
    T * alpha (not differentiable). Gradients flow to means2d, conics, opacities, features and background.
    """
    return _RasterizeToPixels.apply(
        means2d, conics, opacities, features, background, extents, depths, drawn, width, height,
        _region_bounds(region, width, height),
    )  # fmt: skip


def _region_bounds(region: tuple[slice, slice] | None, width: int, height: int) -> np.ndarray:
    """(row_start, row_stop, col_start, col_stop) int64 of a (rows, cols) pair of step-1 slices."""
    if region is None:
        return np.array([0, height, 0, width], dtype=np.int64)
    (row_start, row_stop, _), (col_start, col_stop, _) = region[0].indices(height), region[1].indices(width)
    return np.array([row_start, row_stop, col_start, col_stop], dtype=np.int64)


def max_weight_in_region(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    extents: torch.Tensor,
    depths: torch.Tensor,
    drawn: torch.Tensor,
    region: torch.Tensor,
) -> torch.Tensor:
    """(N,) the largest blending weight T * alpha each Gaussian has at any pixel of `region` (H, W) bool,
    composited as `rasterize_to_pixels` does; 0 for Gaussians that reach none of its pixels."""
    height, width = region.shape
    depth_array = _array(depths)
    depth_keys = depth_array.view(np.uint32 if depth_array.itemsize == 4 else np.uint64)
    offsets, tile_gaussians = kernels.bin_gaussians(
        _array(means2d), _array(extents), depth_keys, 8 * depth_array.itemsize, _array(drawn), width, height, TILE_SIZE,
        _region_bounds(None, width, height), numba.get_num_threads(),
    )  # fmt: skip
    per_intersection = kernels.max_pixel_weights(
        _array(means2d), _array(conics), _array(opacities), offsets, tile_gaussians, _array(region), TILE_SIZE
    )
    out = np.zeros(means2d.shape[0], dtype=per_intersection.dtype)
    np.maximum.at(out, tile_gaussians, per_intersection)
    return torch.from_numpy(out)
