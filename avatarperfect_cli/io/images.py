"""Images (PNG, JPEG, ... via Pillow) <-> float32 tensors (H, W, C) in [0, 1]."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from PIL import Image

from avatarperfect_cli.errors import InputFileError
from avatarperfect_cli.io.atomic import atomic_path
from avatarperfect_cli.io.paths import require_file

ImageMode = Literal["RGB", "RGBA", "L"]
_CHANNELS = (1, 3, 4)  # written as L, RGB, RGBA


def _sixteen_bit_gray(image: Image.Image, mode: ImageMode) -> np.ndarray:
    """(H, W, C) float32 from a 16-bit grayscale image (Pillow's own conversion would clip it to 8 bits)."""
    gray = np.asarray(image, dtype=np.float32)[..., None] / 65535.0
    if mode == "L":
        return gray
    channels = [gray] * 3 + ([np.ones_like(gray)] if mode == "RGBA" else [])
    return np.concatenate(channels, axis=-1)


def image_size(path: Path | str) -> tuple[int, int]:
    """(width, height) of an image file, from its header (nothing is decoded)."""
    path = Path(path)
    require_file(path)
    try:
        with Image.open(path) as image:
            return image.size
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as error:
        raise InputFileError(path, f"not a readable image ({error})") from None


def read_image(path: Path | str, mode: ImageMode | None = None) -> torch.Tensor:
    """(H, W, C) float32 in [0, 1]. mode None keeps alpha when the file has it (C = 4) and gives RGB otherwise
    (C = 3); "RGB" drops alpha, "RGBA" adds an opaque one, "L" gives luminance (C = 1)."""
    path = Path(path)
    require_file(path)
    try:
        with Image.open(path) as image:
            image.load()
            target: ImageMode = mode or ("RGBA" if image.has_transparency_data else "RGB")
            if image.mode.startswith("I;16"):
                pixels = _sixteen_bit_gray(image, target)
            elif image.mode in ("I", "F"):
                raise InputFileError(path, f"unsupported pixel format '{image.mode}' (use 8- or 16-bit images)")
            else:
                converted = np.asarray(image.convert(target), dtype=np.float32)
                pixels = converted.reshape(image.height, image.width, -1) / 255.0
    except (OSError, ValueError, Image.DecompressionBombError) as error:
        raise InputFileError(path, f"not a readable image ({error})") from None
    return torch.from_numpy(np.ascontiguousarray(pixels))


def write_image(path: Path | str, image: torch.Tensor) -> None:
    """Write (H, W), (H, W, 1), (H, W, 3) or (H, W, 4) values in [0, 1] (clipped) as 8 bits per channel, atomically.

    The format follows the suffix of `path`.
    """
    pixels = image.detach().cpu().float()
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    if pixels.ndim != 3 or pixels.shape[2] not in _CHANNELS:
        raise ValueError(f"image has shape {tuple(image.shape)}, expected (H, W) or (H, W, 1|3|4)")
    if not torch.isfinite(pixels).all():
        raise ValueError("image contains NaN or Inf")
    array = (pixels.clamp(0.0, 1.0) * 255.0).round().to(torch.uint8).numpy()
    with atomic_path(path) as temporary:
        Image.fromarray(array[..., 0] if array.shape[2] == 1 else array).save(temporary)


_ENDINGS = {".png": b"IEND\xaeB`\x82", ".jpg": b"\xff\xd9", ".jpeg": b"\xff\xd9"}  # what a whole file ends with


def whole_image(path: Path | str) -> bool:
    """Whether `path` holds a whole image now: a PNG or JPEG ends as its format ends (IEND chunk, EOI marker),
    and every image decodes to its last pixel. False for a file an editor is still writing."""
    path = Path(path)
    try:
        data = path.read_bytes()
        ending = _ENDINGS.get(path.suffix.lower())
        if ending is not None and not data.rstrip(b"\x00").endswith(ending):
            return False
        with Image.open(io.BytesIO(data)) as image:
            image.load()
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError):
        return False
    return True
