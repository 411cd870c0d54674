"""`rasterization()`: the one rendering entry point, in the style of `gsplat.rasterization`."""

from __future__ import annotations

from collections.abc import Callable

import torch

from avatarperfect_cli.gaussians.sh_kernels import eval_sh_cpu
from avatarperfect_cli.render.camera import Camera
from avatarperfect_cli.render.cpu import rasterize_to_pixels
from avatarperfect_cli.render.projection import project_gaussians


class RenderOutput:
    """What one render returns.

    image:      (H, W, C) composited features over the background
    alpha:      (H, W) accumulated opacity, 1 - final transmittance
    depth:      (H, W) expected camera z, metres (sum T*alpha*z / alpha), or None; 0 where alpha = 0
    visibility: (N,) sum over pixels of T * alpha per Gaussian (paper's v_i^I), not differentiable.
                May be given as a function of no arguments: it is then called on the first read (the CUDA
                backend computes it with an extra pass, which training never needs)
    means2d:    (N, 2) projected centres, pixels; call .retain_grad() before backward to read the
                screen-space gradient used by densification
    radii:      (N,) int32 footprint radius, pixels; 0 where the Gaussian was not drawn
    """

    def __init__(
        self,
        image: torch.Tensor,
        alpha: torch.Tensor,
        depth: torch.Tensor | None,
        visibility: torch.Tensor | Callable[[], torch.Tensor],
        means2d: torch.Tensor,
        radii: torch.Tensor,
        width: int,
        height: int,
    ) -> None:
        self.image, self.alpha, self.depth = image, alpha, depth
        self._visibility = visibility
        self.means2d, self.radii, self.width, self.height = means2d, radii, width, height

    @property
    def visibility(self) -> torch.Tensor:
        if callable(self._visibility):
            self._visibility = self._visibility()
        return self._visibility


def rasterization(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    camera: Camera,
    *,
    sh_degree: int | None = None,
    background: torch.Tensor | None = None,
    render_depth: bool = False,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    region: tuple[slice, slice] | None = None,
    backend: str = "auto",
) -> RenderOutput:
    """Render Gaussians into one camera; differentiable w.r.t. every Gaussian parameter.

    means (N, 3) metres, world frame; quats (N, 4) w x y z (normalised here); scales (N, 3)
    standard deviations, metres; opacities (N,) in [0, 1];
    colors: (N, C) per-Gaussian features of any channel count when sh_degree is None, else
    (N, K, 3) SH coefficients with K >= (sh_degree + 1)^2, evaluated for the view direction;
    background: (C,) colour behind the Gaussians, default zeros.
    region: (rows, cols) slices of the pixels a caller reads, e.g. a loss's crop (default: all). Outside
    it the image is the background with alpha 0 and no gradient; the CPU backend composites nothing
    there (its `visibility` then counts the region's pixels alone; read visibility without a region).
    backend: "cpu" (numba kernels), "cuda" (gsplat) or "auto" (cuda for CUDA tensors).
    """
    if backend == "auto":
        backend = "cuda" if means.is_cuda else "cpu"
    if backend == "cuda":
        from avatarperfect_cli.render.gsplat_backend import rasterization_gsplat

        out = rasterization_gsplat(
            means, quats, scales, opacities, colors, camera, sh_degree=sh_degree, background=background,
            render_depth=render_depth, near_plane=near_plane, far_plane=far_plane, eps2d=eps2d,
        )  # fmt: skip
        return out if region is None else _outside_region_cleared(out, region, background)
    if backend != "cpu":
        raise ValueError(f"unknown backend '{backend}': use auto, cpu or cuda")

    camera = camera.to(dtype=means.dtype)
    projection = project_gaussians(means, quats, scales, opacities, camera, near_plane, far_plane, eps2d)
    if sh_degree is not None:
        features = eval_sh_cpu(colors, means - camera.center, sh_degree)
    else:
        features = colors
    channels = features.shape[1]
    if background is None:
        background = torch.zeros(channels, dtype=means.dtype)
    if render_depth:
        features = torch.cat([features, projection.depths[:, None]], dim=1)
        background = torch.cat([background.to(means.dtype), background.new_zeros(1)])
    image, alpha, visibility = rasterize_to_pixels(
        projection.means2d, projection.conics, opacities, features, background.to(means.dtype),
        projection.extents, projection.depths, projection.drawn, camera.width, camera.height, region,
    )  # fmt: skip
    depth = None
    if render_depth:
        depth = torch.where(alpha > 0, image[..., channels] / alpha.clamp_min(1e-10), torch.zeros_like(alpha))
        image = image[..., :channels]
    return RenderOutput(
        image, alpha, depth, visibility, projection.means2d, projection.radii, camera.width, camera.height
    )


def _outside_region_cleared(out: RenderOutput, region: tuple[slice, slice], background: torch.Tensor | None) -> RenderOutput:
    """`out` with the pixels outside `region` set to the background (alpha 0, depth 0), as the CPU
    backend leaves them. The visibility keeps every pixel's share: the CUDA backend composites them all."""
    inside = torch.zeros_like(out.alpha, dtype=torch.bool)
    inside[region] = True
    fill = torch.zeros(out.image.shape[-1], dtype=out.image.dtype, device=out.image.device)
    if background is not None:
        fill = background.to(out.image)
    out.image = torch.where(inside[..., None], out.image, fill)
    out.alpha = torch.where(inside, out.alpha, torch.zeros_like(out.alpha))
    if out.depth is not None:
        out.depth = torch.where(inside, out.depth, torch.zeros_like(out.depth))
    return out
