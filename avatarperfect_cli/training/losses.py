"""Image losses of avatar fitting: L1, SSIM and their GART combination, on the subject's bounding box.

Images are (H, W, C) tensors (the rasterizer's layout), colours in [0, 1].

SSIM uses an 11x11 Gaussian window (sigma = 1.5, applied as two separable 11-tap passes) with
C1 = 0.01^2 and C2 = 0.03^2 (dynamic range 1). Two paddings:
- 'same':  the window is zero padded at the image border and every pixel is averaged, exactly as
           3DGS's `ssim` (conv2d with padding = 5); used for the training loss.
- 'valid': only pixels whose whole window lies inside the image are averaged (scikit-image,
           torchmetrics and pytorch-msssim style); used for the evaluation metric.
On the CPU a numba kernel computes the map and its analytic gradient (a few ms at 512^2);
elsewhere (CUDA) grouped conv2d and autograd do.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numba
import numpy as np
import torch
import torch.nn.functional as F

from avatarperfect_cli.training import ssim_kernels

SSIM_WINDOW = ssim_kernels.WINDOW  # 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2

Padding = Literal["same", "valid"]


def gaussian_taps(dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(11,) normalised 1D Gaussian window (sigma 1.5); the 2D window is its outer product."""
    offsets = torch.arange(SSIM_WINDOW, dtype=torch.float64) - SSIM_WINDOW // 2
    taps = torch.exp(-(offsets**2) / (2.0 * SSIM_SIGMA**2))
    return (taps / taps.sum()).to(dtype)


def _border(padding: Padding) -> int:
    if padding not in ("same", "valid"):
        raise ValueError(f"padding must be 'same' or 'valid', got {padding!r}")
    return 0 if padding == "same" else SSIM_WINDOW // 2


class _SSIMNumba(torch.autograd.Function):
    """Mean SSIM of two (H, W, C) CPU images through the numba kernels, with the analytic backward."""

    @staticmethod
    def forward(ctx, pred: torch.Tensor, target: torch.Tensor, border: int) -> torch.Tensor:  # type: ignore[override]
        height, width, channels = pred.shape
        x = pred.detach().contiguous().reshape(height, width * channels).numpy()
        y = target.detach().to(pred.dtype).contiguous().reshape(height, width * channels).numpy()
        taps = gaussian_taps(pred.dtype).numpy()
        derivative_maps = 4 if ctx.needs_input_grad[1] else 3 if ctx.needs_input_grad[0] else 0
        row_sums, derivatives = ssim_kernels.ssim_forward(
            x, y, taps, SSIM_C1, SSIM_C2, border, channels, derivative_maps, numba.get_num_threads()
        )
        count = (height - 2 * border) * (width - 2 * border) * channels
        ctx.shape, ctx.count, ctx.channels = pred.shape, count, channels
        ctx.arrays = (x, y, taps, derivatives)
        return torch.tensor(row_sums.sum() / count, dtype=pred.dtype)

    @staticmethod
    def backward(  # type: ignore[override]
        ctx, grad_output: torch.Tensor
    ) -> tuple[torch.Tensor | None, torch.Tensor | None, None]:
        x, y, taps, derivatives = ctx.arrays
        scale = float(grad_output) / ctx.count
        grad_x, grad_y = ssim_kernels.ssim_backward(
            derivatives, taps, x, y, ctx.channels, scale, numba.get_num_threads()
        )
        grad_pred = torch.from_numpy(grad_x).reshape(ctx.shape) if ctx.needs_input_grad[0] else None
        grad_target = torch.from_numpy(grad_y).reshape(ctx.shape) if ctx.needs_input_grad[1] else None
        return grad_pred, grad_target, None


def _ssim_conv(pred: torch.Tensor, target: torch.Tensor, border: int) -> torch.Tensor:
    """Mean SSIM through grouped separable conv2d (any device; autograd gives the gradient)."""
    channels = pred.shape[-1]
    x = pred.permute(2, 0, 1)[None]
    y = target.to(pred.dtype).permute(2, 0, 1)[None]
    taps = gaussian_taps(pred.dtype).to(pred.device)
    radius = SSIM_WINDOW // 2
    stacked = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    groups = stacked.shape[1]
    stacked = F.conv2d(stacked, taps.view(1, 1, 1, -1).expand(groups, 1, 1, -1), padding=(0, radius), groups=groups)
    stacked = F.conv2d(stacked, taps.view(1, 1, -1, 1).expand(groups, 1, -1, 1), padding=(radius, 0), groups=groups)
    mx, my, sxx, syy, sxy = stacked.split(channels, dim=1)
    a1 = 2.0 * mx * my + SSIM_C1
    a2 = 2.0 * (sxy - mx * my) + SSIM_C2
    b1 = mx * mx + my * my + SSIM_C1
    b2 = (sxx - mx * mx) + (syy - my * my) + SSIM_C2
    ssim_map = a1 * a2 / (b1 * b2)
    if border:
        ssim_map = ssim_map[..., border:-border, border:-border]
    return ssim_map.mean()


def ssim(pred: torch.Tensor, target: torch.Tensor, padding: Padding = "same") -> torch.Tensor:
    """Mean SSIM over pixels and channels of two (H, W, C) images; a differentiable scalar tensor.

    padding: 'same' (3DGS's zero-padded SSIM, the training loss) or 'valid' (the usual metric); see
    the module docstring. 'valid' needs H, W >= 11.
    """
    if pred.ndim != 3 or pred.shape != target.shape:
        shapes = f"{tuple(pred.shape)} and {tuple(target.shape)}"
        raise ValueError(f"expected two (H, W, C) images of one shape, got {shapes}")
    border = _border(padding)
    if min(pred.shape[0], pred.shape[1]) <= 2 * border:
        raise ValueError(f"a {pred.shape[0]}x{pred.shape[1]} image is too small for '{padding}' SSIM")
    if pred.device.type == "cpu" and pred.dtype in (torch.float32, torch.float64):
        return _SSIMNumba.apply(pred, target, border)
    return _ssim_conv(pred, target, border)


def l1_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean absolute difference of two images of one shape."""
    return (pred - target).abs().mean()


def image_loss(
    pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None, ssim_weight: float = 0.1
) -> torch.Tensor:
    """GART's image loss L1 + ssim_weight * (1 - SSIM) of two (H, W, C) images ('same' SSIM).

    mask: optional (H, W) weights in [0, 1] (the edit mask M_k); the loss is then the paper's
    L(M * pred, M * target): both images are multiplied by the mask and every pixel still counts in
    the means, so pixels outside the mask contribute zero.
    """
    if mask is not None:
        weights = mask.to(pred.dtype)[..., None]
        pred, target = pred * weights, target * weights
    return l1_loss(pred, target) + ssim_weight * (1.0 - ssim(pred, target))


DATASET_BACKGROUND = 1.0  # the colour the dataset loader composites the frames onto (white)


def boundary_band(mask: torch.Tensor, width: int) -> torch.Tensor:
    """(H, W) bool: the pixels within `width` of the (H, W) bool mask's edge, inside it or outside (square
    neighbourhoods; the image border is no edge), on the mask's device (computed by OpenCV on the CPU)."""
    kernel = np.ones((2 * width + 1, 2 * width + 1), np.uint8)
    pixels = mask.cpu().numpy().astype(np.uint8)
    return torch.from_numpy(cv2.dilate(pixels, kernel) != cv2.erode(pixels, kernel)).to(mask.device)


@dataclass
class BandPixels:
    """The pixels of a frame's mask band where the frame's colours decide (`band_pixels`).

    index: (K,) int64 flat indices into the (H, W) image; frame: (K, 3) the frame's colours there;
    backdrop: (K, 3) what lies behind the subject there.
    """

    index: torch.Tensor
    frame: torch.Tensor
    backdrop: torch.Tensor


def band_pixels(band: torch.Tensor, frame: torch.Tensor, backdrop: torch.Tensor | float) -> BandPixels:
    """The pixels of `band` (H, W) bool, a mask's `boundary_band`, whose backdrop is known, with their colours:
    frame (H, W, 3) the frame's colours with `backdrop` behind its subject; backdrop (H, W, 3), NaN where
    unknown, or one colour. A frame's band is fixed, so a trainer gathers it once, not at every step."""
    backdrop = torch.as_tensor(backdrop, dtype=frame.dtype, device=frame.device).expand_as(frame)
    index = (band & ~backdrop.isnan().any(dim=-1)).flatten().nonzero()[:, 0]
    return BandPixels(index, frame.reshape(-1, 3)[index], backdrop.reshape(-1, 3)[index])


def mask_band_supervision(
    image: torch.Tensor, alpha: torch.Tensor, background: torch.Tensor, target: torch.Tensor, band: BandPixels
) -> tuple[torch.Tensor, torch.Tensor]:
    """The render and target of a video frame whose mask may be a few pixels off at its edge: the silhouette
    is evidence there, not truth.

    image: (H, W, 3) render over `background` (3,); alpha: (H, W) its accumulated opacity; target: (H, W, 3)
    the frame on the mask and `background` elsewhere; band: the `band_pixels` of the frame's mask. There the
    render composited over the backdrop is compared with the frame, so the frame's colours, not the mask,
    decide whether a pixel is subject or background; where the backdrop is unknown the mask decides, as
    outside the band. Returns the render and the target, (H, W, 3) each.
    """
    shape, index = image.shape, band.index
    pixels = image.reshape(-1, 3)
    on_backdrop = pixels[index] + (1.0 - alpha.reshape(-1)[index, None]) * (band.backdrop - background)
    image = pixels.index_put((index,), on_backdrop).reshape(shape)
    return image, target.reshape(-1, 3).index_put((index,), band.frame).reshape(shape)


def subject_bbox(mask: torch.Tensor, margin: int = 20) -> tuple[slice, slice]:
    """Row and column slices of the (H, W) mask's non-zero pixels grown by `margin` pixels.

    Clipped to the image; the whole image when the mask is empty. GART computes its losses on this
    crop (margin 20 px): `pred[rows, cols]`.
    """
    height, width = mask.shape
    rows = torch.nonzero(mask.any(dim=1)).flatten()
    cols = torch.nonzero(mask.any(dim=0)).flatten()
    if rows.numel() == 0:
        return slice(0, height), slice(0, width)
    top, bottom = int(rows[0]) - margin, int(rows[-1]) + 1 + margin
    left, right = int(cols[0]) - margin, int(cols[-1]) + 1 + margin
    return slice(max(top, 0), min(bottom, height)), slice(max(left, 0), min(right, width))
