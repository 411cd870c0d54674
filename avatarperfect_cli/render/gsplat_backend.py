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
    gradient of the summed one-channel image w.r.t. per-Gaussian features, so it costs one more forward and
    backward; it is computed only when `RenderOutput.visibility` is read (training never reads it).

    gsplat's projected centres are (1, N, 2) (one camera); the (N, 2) `means2d` returned is a leaf whose
    `.grad` a hook on gsplat's tensor fills during backward, so densification reads the screen-space
    gradient as it does on the CPU.
    """
    gsplat_rasterization = _gsplat_rasterization()
    camera = camera.to(device=means.device, dtype=means.dtype)
    common = dict(
        viewmats=camera.world_to_camera[None], Ks=camera.K[None], width=camera.width, height=camera.height,
        near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, packed=False,
    )  # fmt: skip
    channels = colors.shape[-1]
    # the background is composited here, as gsplat would (+ T * background), because gsplat's versions
    # differ in whether they extend it for the depth channel themselves
    image, alpha, info = gsplat_rasterization(
        means, quats, scales, opacities, colors, sh_degree=sh_degree, render_mode="RGB+ED" if render_depth else "RGB",
        **common,
    )  # fmt: skip
    detached = [tensor.detach() for tensor in (means, quats, scales, opacities)]

    def visibility() -> torch.Tensor:
        with torch.enable_grad():
            unit = torch.zeros(means.shape[0], 1, device=means.device, dtype=means.dtype, requires_grad=True)
            weight_image, _, _ = gsplat_rasterization(*detached, unit, **common)
            (gradient,) = torch.autograd.grad(weight_image.sum(), unit)
        return gradient[:, 0]

    radii = info["radii"][0]
    if radii.ndim == 2:  # gsplat >= 1.5 returns a radius per image axis
        radii = radii.max(dim=-1).values
    depth = image[0, ..., channels] if render_depth else None
    image, alpha = image[0, ..., :channels], alpha[0]
    if background is not None:
        image = image + (1.0 - alpha) * background.to(image)
    return RenderOutput(
        image, alpha[..., 0], depth, visibility, _screen_means(info["means2d"]),
        radii.to(torch.int32), camera.width, camera.height,
    )  # fmt: skip


def _screen_means(batched: torch.Tensor) -> torch.Tensor:
    """(N, 2) leaf holding gsplat's (1, N, 2) projected centres; backward through gsplat adds their gradient
    to its `.grad` (gsplat's tensor feeds the rasterizer directly, so a slice of it would get no gradient)."""
    leaf = batched.detach()[0].requires_grad_(batched.requires_grad)
    if batched.requires_grad:

        def store(grad: torch.Tensor) -> None:
            leaf.grad = grad[0].clone() if leaf.grad is None else leaf.grad + grad[0]

        batched.register_hook(store)
    return leaf
