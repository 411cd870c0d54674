"""CUDA backend: the same call through `gsplat.rasterization` (imported only when used)."""

from __future__ import annotations

import torch

from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.render.camera import Camera
from avatarperfect_cli.render.rasterization import RenderOutput


def _gsplat_rasterization():
    if not torch.cuda.is_available():
        raise AvatarPerfectError("the cuda backend needs a CUDA GPU; use --device cpu")
    try:
        from gsplat import rasterization
    except ImportError as error:
        raise AvatarPerfectError(f"the cuda backend needs gsplat: pip install 'avatarperfect-cli[cuda]' ({error})") from None
    return rasterization


def rasterization_gsplat(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    camera: Camera,
    *,
    sh_degree: int | None,
    background: torch.Tensor | None,
    render_depth: bool,
    near_plane: float,
    far_plane: float,
    eps2d: float,
) -> RenderOutput:
    """`rasterization()` on CUDA tensors. Visibility sum_p T*alpha per Gaussian is exact: it is the
    gradient of the summed one-channel image w.r.t. per-Gaussian features, so it costs one backward.
    """
    gsplat_rasterization = _gsplat_rasterization()
    camera = camera.to(device=means.device, dtype=means.dtype)
    common = dict(
        viewmats=camera.world_to_camera[None], Ks=camera.K[None], width=camera.width, height=camera.height,
        near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, packed=False,
    )  # fmt: skip
    channels = colors.shape[-1]
    backgrounds = None
    if background is not None:
        backgrounds = background.to(means)[None]
        if render_depth:
            backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(1, 1)], dim=1)
    image, alpha, info = gsplat_rasterization(
        means, quats, scales, opacities, colors, sh_degree=sh_degree, backgrounds=backgrounds,
        render_mode="RGB+ED" if render_depth else "RGB", **common,
    )  # fmt: skip
    with torch.enable_grad():
        unit = torch.zeros(means.shape[0], 1, device=means.device, dtype=means.dtype, requires_grad=True)
        weight_image, _, _ = gsplat_rasterization(
            means.detach(), quats.detach(), scales.detach(), opacities.detach(), unit, **common
        )
        (visibility,) = torch.autograd.grad(weight_image.sum(), unit)
    radii = info["radii"][0]
    if radii.ndim == 2:  # gsplat >= 1.5 returns a radius per image axis
        radii = radii.max(dim=-1).values
    depth = image[0, ..., channels] if render_depth else None
    return RenderOutput(
        image[0, ..., :channels], alpha[0, ..., 0], depth, visibility[:, 0], info["means2d"][0],
        radii.to(torch.int32), camera.width, camera.height,
    )  # fmt: skip
