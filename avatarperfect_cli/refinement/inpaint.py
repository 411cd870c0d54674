"""Fill tools for a selected region (paper §6.1): a flat colour (the inpaint tool), OpenCV's inpainting from the
surrounding pixels, and Stable-Diffusion inpainting with several candidates (the diffusion-inpaint tool).

Images are (H, W, 3) float32 sRGB in [0, 1]; a region is (H, W) bool. Every fill changes pixels inside the region
only.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch
from PIL import Image, ImageColor

from avatarperfect_cli.errors import AvatarPerfectError, InputFileError

if TYPE_CHECKING:
    from diffusers import DiffusionPipeline

OPENCV_METHODS = {"telea": cv2.INPAINT_TELEA, "ns": cv2.INPAINT_NS}
OPENCV_RADIUS = 5  # px of surrounding pixels each filled pixel draws on
CONTEXT_FRACTION = 0.25  # the diffusion crop adds this share of the region's size on every side ...
MIN_CROP_SIDE = 128  # ... and spans at least this many pixels, so the model sees what surrounds a small region
_NUMBER = r"\s*([0-9]*\.?[0-9]+)\s*"
_TRIPLET = re.compile(rf"{_NUMBER},{_NUMBER},{_NUMBER}")
_OFFLINE_ENVIRONMENT = {
    "HF_HUB_OFFLINE": "1",
    "TRANSFORMERS_OFFLINE": "1",
    "HF_HUB_DISABLE_TELEMETRY": "1",
    "TRANSFORMERS_VERBOSITY": "error",
}
_INSTALL_HINT = 'the diffusion fill needs diffusers and transformers: pip install "avatarperfect-cli[inpaint]"'


def parse_colour(text: str) -> tuple[float, float, float]:
    """sRGB in [0, 1] from a name ("white"), "#rgb", "#rrggbb", or "R,G,B": on the 0..1 scale when a component is
    written with a decimal point ("1.0,0.5,0"), otherwise on 0..255 ("255,128,0")."""
    triplet = _TRIPLET.fullmatch(text)
    if triplet is not None:
        values = [float(value) for value in triplet.groups()]
        scale = 1.0 if "." in text else 255.0
        if max(values) > scale:
            raise AvatarPerfectError(f"colour '{text}': components are 0..255, or 0..1 written with a decimal point")
        return (values[0] / scale, values[1] / scale, values[2] / scale)
    try:
        red, green, blue = ImageColor.getcolor(text.strip(), "RGB")
    except ValueError:
        raise AvatarPerfectError(
            f"'{text}' is not a colour (use a name such as white, #rrggbb, or R,G,B in 0..255 or 0..1)"
        ) from None
    if not all(0 <= value <= 255 for value in (red, green, blue)):  # Pillow passes rgb(300,0,0) through
        raise AvatarPerfectError(f"colour '{text}' is out of range: it gives ({red}, {green}, {blue}), components are 0..255")
    return (red / 255.0, green / 255.0, blue / 255.0)


def _check_region(image: torch.Tensor, region: torch.Tensor) -> None:
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image has shape {tuple(image.shape)}, expected (H, W, 3)")
    if tuple(region.shape) != tuple(image.shape[:2]):
        raise AvatarPerfectError(
            f"the region is {region.shape[1]}x{region.shape[0]} pixels, the image {image.shape[1]}x{image.shape[0]}"
        )


def fill_flat(image: torch.Tensor, region: torch.Tensor, colour: tuple[float, float, float]) -> torch.Tensor:
    """(H, W, 3) copy of `image` with `region` set to `colour` (sRGB in [0, 1])."""
    _check_region(image, region)
    filled = image.clone()
    filled[region] = torch.tensor(colour, dtype=image.dtype)
    return filled


def fill_opencv(image: torch.Tensor, region: torch.Tensor, method: str) -> torch.Tensor:
    """(H, W, 3) copy of `image` with `region` filled from the pixels around it by cv2.inpaint: "telea" (fast
    marching) or "ns" (Navier-Stokes), within OPENCV_RADIUS px; each channel as float32 on 0..255, so nothing is
    quantised (OpenCV's Telea gives wrong values for floats on 0..1)."""
    _check_region(image, region)
    if method not in OPENCV_METHODS:
        raise AvatarPerfectError(f"unknown fill method '{method}' (use one of: {', '.join(OPENCV_METHODS)})")
    if not region.any():
        return image.clone()
    if region.all():
        raise AvatarPerfectError("the region covers the whole image: there is nothing around it to fill from")
    mask = region.cpu().numpy().astype(np.uint8)
    levels = image.detach().cpu().float().numpy() * 255.0
    flags = OPENCV_METHODS[method]
    channels = [cv2.inpaint(np.ascontiguousarray(levels[..., c]), mask, OPENCV_RADIUS, flags) for c in range(3)]
    filled = image.clone()
    filled[region] = (torch.from_numpy(np.stack(channels, axis=-1))[region] / 255.0).to(image.dtype)
    return filled


@contextmanager
def _offline_hub() -> Iterator[None]:
    """Hugging Face libraries may not reach the network (nor print their import chatter) inside the block."""
    saved = {name: os.environ.get(name) for name in _OFFLINE_ENVIRONMENT}
    os.environ.update(_OFFLINE_ENVIRONMENT)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _load_pipeline(model_dir: Path) -> DiffusionPipeline:
    if not (model_dir / "model_index.json").is_file():
        raise InputFileError(model_dir, "no diffusers pipeline here (model_index.json is missing)")
    try:
        from diffusers import AutoPipelineForInpainting
        from diffusers.utils import logging as diffusers_logging
        from transformers.utils import logging as transformers_logging  # the pipelines' text encoders
    except ImportError:
        raise AvatarPerfectError(_INSTALL_HINT) from None
    for library in (diffusers_logging, transformers_logging):
        library.set_verbosity_error()
        library.disable_progress_bar()
    try:
        pipeline = AutoPipelineForInpainting.from_pretrained(model_dir, local_files_only=True)
    except Exception as error:  # noqa: BLE001  a user's model folder fails in many libraries' own ways
        reason = str(error).strip().splitlines()[0] if str(error).strip() else ""
        problem = f"cannot load the inpainting pipeline: {type(error).__name__} {reason}"
        raise InputFileError(model_dir, problem) from None
    if getattr(pipeline, "unet", None) is None:
        raise InputFileError(model_dir, f"a {type(pipeline).__name__}, not a Stable Diffusion inpainting pipeline")
    pipeline.set_progress_bar_config(disable=True)
    return pipeline.to("cuda" if torch.cuda.is_available() else "cpu")


def _square_around(region: torch.Tensor) -> tuple[int, int, int]:
    """(top, left, side): a square holding the region's bounding box with context on every side, moved inside
    the image where it fits (it may reach outside an image smaller than the square)."""
    height, width = region.shape
    ys, xs = torch.nonzero(region, as_tuple=True)
    top, bottom, left, right = int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1
    extent = max(bottom - top, right - left)
    side = max(MIN_CROP_SIDE, round((1.0 + 2.0 * CONTEXT_FRACTION) * extent))
    square_top = (top + bottom - side) // 2
    square_left = (left + right - side) // 2
    if side <= height:
        square_top = min(max(square_top, 0), height - side)
    if side <= width:
        square_left = min(max(square_left, 0), width - side)
    return square_top, square_left, side


def _crop(pixels: np.ndarray, top: int, left: int, side: int) -> np.ndarray:
    """The side x side window at (top, left) of (H, W, ...) `pixels`, edge pixels repeated outside the image."""
    height, width = pixels.shape[:2]
    pad = ((max(0, -top), max(0, top + side - height)), (max(0, -left), max(0, left + side - width)))
    padded = np.pad(pixels, pad + ((0, 0),) * (pixels.ndim - 2), mode="edge")
    row, column = max(top, 0), max(left, 0)  # where the window starts in `padded`
    return padded[row : row + side, column : column + side]


def _resize(pixels: np.ndarray, side: int) -> np.ndarray:
    interpolation = cv2.INTER_AREA if side < pixels.shape[0] else cv2.INTER_CUBIC
    return cv2.resize(pixels, (side, side), interpolation=interpolation)


def _step_callback(on_step: Callable[[int, int], None], candidate: int, steps: int, candidates: int) -> Callable:
    """A diffusers `callback_on_step_end` for candidate `candidate`: on_step(steps done, steps in all candidates)."""

    def callback(pipeline: object, step: int, timestep: object, tensors: dict) -> dict:
        on_step(candidate * steps + step + 1, candidates * steps)
        return tensors

    return callback


def fill_diffusion(
    image: torch.Tensor,
    region: torch.Tensor,
    model_dir: Path,
    prompt: str = "",
    candidates: int = 3,
    seed: int = 0,
    steps: int = 30,
    on_step: Callable[[int, int], None] | None = None,
) -> list[torch.Tensor]:
    """`candidates` (H, W, 3) copies of `image`, each with `region` repainted by the diffusers inpainting pipeline
    in `model_dir` (loaded offline); candidate i comes from seed + i alone (one pipeline run each).

    A square crop around the region (with context) is resized to the pipeline's native size (UNet sample size x
    VAE scale factor: 512 for SD 1.5/2 inpainting), repainted under the region grown by one latent pixel, resized
    back, and pasted inside the region only. on_step(done, total) follows the denoising steps of all candidates.
    """
    _check_region(image, region)
    if not region.any():
        return [image.clone() for _ in range(candidates)]
    with _offline_hub():
        pipeline = _load_pipeline(Path(model_dir))
        native = pipeline.unet.config.sample_size * pipeline.vae_scale_factor
        top, left, side = _square_around(region)
        pixels = (image.detach().cpu().float().clamp(0.0, 1.0).numpy() * 255.0).round().astype(np.uint8)
        crop = _resize(_crop(pixels, top, left, side), native)
        grow = np.ones((2 * pipeline.vae_scale_factor + 1,) * 2, np.uint8)
        crop_region = _crop(region.cpu().numpy().astype(np.uint8) * 255, top, left, side)
        repaint = cv2.dilate((_resize(crop_region, native) > 0).astype(np.uint8) * 255, grow)
        outputs = [
            pipeline(
                prompt=prompt,
                image=Image.fromarray(crop),
                mask_image=Image.fromarray(repaint),
                height=native,
                width=native,
                num_inference_steps=steps,
                generator=torch.Generator(pipeline.device).manual_seed(seed + index),
                output_type="np",
                callback_on_step_end=None if on_step is None else _step_callback(on_step, index, steps, candidates),
            ).images[0]
            for index in range(candidates)
        ]
    ys, xs = torch.nonzero(region, as_tuple=True)
    results = []
    for output in outputs:
        painted = torch.from_numpy(_resize(np.asarray(output, dtype=np.float32), side)).clamp(0.0, 1.0)
        filled = image.clone()
        filled[ys, xs] = painted[ys - top, xs - left].to(image.dtype)
        results.append(filled)
    return results
