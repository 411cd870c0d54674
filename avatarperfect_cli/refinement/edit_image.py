"""A painted image -> an edit (paper §6.1): which pixels changed, which mean "background", which colours to learn.

The user paints over `suggested.png` (the render on white) in any editor. A pixel is **changed** when one of its
channels differs from the render by more than `tolerance`. Changed pixels that are white (every channel
>= 1 - tolerance) or transparent (alpha < 0.5) are the background tool; every other changed pixel is a colour target.

Two kinds of change are not edits:
- **speckles**: 8-connected groups of fewer than `MIN_STROKE_PIXELS` changed pixels (re-encoding noise above the
  tolerance) are dropped;
- **the anti-aliasing seam**: a brush stroke's border blends the render colour R with the paint colour C. A changed
  pixel within `SEAM_WIDTH` px of an unchanged one is tested against the changed pixels in its (2 SEAM_WIDTH + 1)²
  window: it is a blend when its colour P lies within `tolerance` of the segment R + t (C - R), t in [0, 1], where C
  is that neighbour's target colour (white for background). Among the colours it blends, the one furthest from R
  (the purest paint) decides: coverage t >= 0.5 joins the stroke with target C (background when that neighbour is
  background), t < 0.5 is dropped from the edit. So no half-and-half colour becomes a target, and a stroke's edit
  ends at its 50% coverage contour.

  White (background) neighbours are always tested; coloured ones only when P is more than `SEAM_MIN_CHANGE`
  tolerances from R. Closer to R, any P lies near some segment from R, so a deliberate subtle edit (a region
  shifted by a few levels) would lose its border; such a pixel keeps its painted colour, which is then that close
  to the render. The test assumes flat paint: a textured region shifted by more than that has its 2-px border
  snapped to neighbouring colours (by up to the texture's variation over 2 px: 15 levels in the tests' texture).

Lossy files (JPEG, WebP) use `LOSSY_TOLERANCE` (4x the default). A JPEG is also compared with the render
compressed the same way (the file's quantisation tables and chroma subsampling): far from the strokes the two decode
to the same pixels, so only the ringing next to strokes remains. Measured on the sample subject at quality 75,
4:2:0, around 2,400 painted pixels: 135 pixels ring beyond 18 levels and 42 beyond 24; against the raw render,
1,055 pixels all along the silhouette differ by more than 24.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
from PIL import Image, ImageCms, JpegImagePlugin

from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.io.images import image_size, read_image
from avatarperfect_cli.io.paths import require_file

DEFAULT_TOLERANCE = 5.5 / 255.0  # ±3 levels of noise (+0.5 against a float render) is no edit, ±6 levels is
LOSSY_TOLERANCE = 4.0 * DEFAULT_TOLERANCE  # 22 levels: JPEG at quality >= 90 rings less next to strokes
MIN_STROKE_PIXELS = 3  # smaller 8-connected groups of changed pixels are noise
SEAM_WIDTH = 2  # px: anti-aliased brush borders blend over 1-2 pixels
SEAM_MIN_CHANGE = 2.5  # tolerances: a seam pixel moved less is not tested against coloured paint (no integer ties)
LOSSY_FORMATS = frozenset({"JPEG", "MPO", "WEBP"})
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_COLOUR_TYPES_WITH_CHANNELS = frozenset({2, 4, 6})  # RGB, grey + alpha, RGBA (0 = grey, 3 = palette)
_SRGB = ImageCms.createProfile("sRGB")


@dataclass(frozen=True)
class JpegEncoding:
    """How a JPEG was compressed, to compress the render the same way: Pillow's `quantization` tables and
    `subsampling` code (0 = 4:4:4, 1 = 4:2:2, 2 = 4:2:0)."""

    quantization: dict[int, list[int]]
    subsampling: int


@dataclass
class PaintedImage:
    """rgb: (H, W, 3) float32 sRGB in [0, 1], transparent pixels composited on white; transparent: (H, W) bool,
    alpha < 0.5; lossy: the file was JPEG or WebP (warn about compression artifacts); jpeg: set for JPEGs."""

    rgb: torch.Tensor
    transparent: torch.Tensor
    lossy: bool
    jpeg: JpegEncoding | None = field(default=None, repr=False)


@dataclass
class EditMasks:
    """edit: (H, W) bool M_k, the pixels refine supervises; background: (H, W) bool subset of `edit`, painted
    white or transparent ("nothing here"); target: (H, W, 3) float32 colours to learn inside `edit`, white at
    background pixels (outside `edit` it is the painted image and means nothing)."""

    edit: torch.Tensor
    background: torch.Tensor
    target: torch.Tensor

    def counts(self) -> dict[str, int]:
        """Pixels edited, painted background and given a colour (edited = background + colour)."""
        edited, background = int(self.edit.sum()), int(self.background.sum())
        return {"edited": edited, "background": background, "colour": edited - background}


def read_painted_image(path: Path | str) -> PaintedImage:
    """Read what an editor saved: RGB, RGBA, L, LA, palette (with or without tRNS), 8- or 16-bit PNG, JPEG, ...

    16-bit colour PNGs are decoded by OpenCV (Pillow keeps 8 bits); an embedded ICC profile other than sRGB is
    converted to sRGB (to 8 bits); every other file goes through `io.read_image`.
    """
    path = Path(path)
    require_file(path)
    try:
        with Image.open(path) as image:
            _refuse_animation(image, path)
            icc_profile = image.info.get("icc_profile")
            if icc_profile and not _is_srgb(icc_profile):
                image.load()
                rgba = _convert_to_srgb(image, icc_profile, path)
            elif _is_sixteen_bit_colour_png(path):
                image.load()  # Pillow notices truncated files; OpenCV only warns on stderr
                rgba = _read_sixteen_bit_colour(path)
            else:
                rgba = None
            lossy, jpeg = image.format in LOSSY_FORMATS, _jpeg_encoding(image)
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as error:
        raise InputFileError(path, f"not a readable image ({error})") from None
    pixels = torch.from_numpy(rgba) if rgba is not None else read_image(path, "RGBA")
    alpha = pixels[..., 3:]
    rgb = (pixels[..., :3] * alpha + (1.0 - alpha)).contiguous()
    return PaintedImage(rgb=rgb, transparent=alpha[..., 0] < 0.5, lossy=lossy, jpeg=jpeg)


def _refuse_animation(image: Image.Image, path: Path) -> None:
    """A GIF keeps at most 256 colours (its quantisation changes pixels nobody painted) and an animation holds
    several images: both are refused in one line."""
    if image.format == "GIF":
        raise InputFileError(path, "a GIF keeps at most 256 colours, which changes pixels you did not paint; save a PNG")
    frames = getattr(image, "n_frames", 1)
    if frames > 1:
        raise InputFileError(path, f"an animation of {frames} frames; save the painted image as a single PNG")


def _is_srgb(icc_profile: bytes) -> bool:
    """True when the profile calls itself sRGB (or cannot be parsed: the pixels are then read as sRGB)."""
    try:
        description = ImageCms.getProfileDescription(ImageCms.ImageCmsProfile(io.BytesIO(icc_profile)))
    except (ImageCms.PyCMSError, OSError, ValueError):
        return True
    return "srgb" in description.casefold()


def _convert_to_srgb(image: Image.Image, icc_profile: bytes, path: Path) -> np.ndarray:
    """(H, W, 4) float32: colours converted from the embedded profile to sRGB, alpha kept."""
    colour_mode = image.mode if image.mode in ("RGB", "L", "CMYK") else ("L" if image.mode in ("LA", "La") else "RGB")
    try:
        rgb = ImageCms.profileToProfile(
            image.convert(colour_mode),
            ImageCms.ImageCmsProfile(io.BytesIO(icc_profile)),
            _SRGB,
            renderingIntent=ImageCms.Intent.RELATIVE_COLORIMETRIC,
            outputMode="RGB",
        )
    except ImageCms.PyCMSError as error:
        raise InputFileError(path, f"cannot convert its colour profile to sRGB ({error})") from None
    alpha = image.convert("RGBA").getchannel("A") if image.has_transparency_data else Image.new("L", image.size, 255)
    return np.dstack([np.asarray(rgb), np.asarray(alpha)]).astype(np.float32) / 255.0


def _is_sixteen_bit_colour_png(path: Path) -> bool:
    """A PNG whose IHDR says 16 bits per sample with colour or alpha (16-bit grey alone Pillow reads in full)."""
    with path.open("rb") as file:
        header = file.read(26)
    is_png = header[:8] == _PNG_SIGNATURE and header[12:16] == b"IHDR"
    return is_png and header[24] == 16 and header[25] in _PNG_COLOUR_TYPES_WITH_CHANNELS


def _read_sixteen_bit_colour(path: Path) -> np.ndarray:
    """(H, W, 4) float32 RGBA from a 16-bit PNG (OpenCV decodes grey + alpha as BGRA)."""
    pixels = cv2.imdecode(np.fromfile(path, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if pixels is None or pixels.dtype != np.uint16 or pixels.ndim != 3:
        raise InputFileError(path, "not a readable 16-bit PNG")
    rgb = pixels[..., 2::-1]
    alpha = pixels[..., 3:] if pixels.shape[2] == 4 else np.full_like(pixels[..., :1], 65535)
    return np.concatenate([rgb, alpha], axis=-1).astype(np.float32) / 65535.0


def _jpeg_encoding(image: Image.Image) -> JpegEncoding | None:
    """The tables and subsampling of a colour (YCbCr) JPEG; None for other files."""
    if image.format not in ("JPEG", "MPO") or image.mode != "RGB":
        return None
    subsampling = JpegImagePlugin.get_sampling(image)
    if subsampling < 0 or not image.quantization:
        return None
    return JpegEncoding({key: list(table) for key, table in image.quantization.items()}, subsampling)


def _jpeg_round_trip(rgb: torch.Tensor, encoding: JpegEncoding) -> torch.Tensor:
    """(H, W, 3) float32: `rgb` as 8 bits, compressed with `encoding` and decoded."""
    levels = (rgb.clamp(0.0, 1.0) * 255.0).round().to(torch.uint8).numpy()
    buffer = io.BytesIO()
    Image.fromarray(levels).save(buffer, "JPEG", qtables=encoding.quantization, subsampling=encoding.subsampling)
    buffer.seek(0)
    with Image.open(buffer) as decoded:
        return torch.from_numpy(np.asarray(decoded.convert("RGB"), dtype=np.float32) / 255.0)


def derive_edit_masks(
    painted: PaintedImage,
    rendered: torch.Tensor,
    tolerance: float | None = None,
    user_mask: torch.Tensor | None = None,
) -> EditMasks:
    """The edit the user painted over `rendered` (H, W, 3) in [0, 1] (see the module docstring for the rules).

    tolerance: in [0, 1] units per channel; None picks DEFAULT_TOLERANCE, or LOSSY_TOLERANCE for lossy files.
    user_mask: (H, W) bool, the user's own selection: then `edit` is exactly this mask (no difference, speckle or
    seam test) and only the background and target rules apply inside it.
    """
    height, width = painted.rgb.shape[:2]
    if tuple(rendered.shape) != (height, width, 3):
        raise AvatarPerfectError(
            f"the edited image is {width}x{height} pixels but the render is {rendered.shape[1]}x{rendered.shape[0]};"
            " paint on the suggested image at its own size"
        )
    if tolerance is None:
        tolerance = LOSSY_TOLERANCE if painted.lossy else DEFAULT_TOLERANCE
    painted_rgb = painted.rgb.float()
    paint_is_background = painted.transparent | (painted_rgb >= 1.0 - tolerance).all(dim=-1)
    target = torch.where(paint_is_background[..., None], torch.ones(3), painted_rgb)
    if user_mask is not None:
        if tuple(user_mask.shape) != (height, width):
            mask_height, mask_width = user_mask.shape[:2]
            raise AvatarPerfectError(f"the mask is {mask_width}x{mask_height} pixels, the image {width}x{height}")
        edit = user_mask.bool()
        return EditMasks(edit=edit, background=edit & paint_is_background, target=target)

    rendered = rendered.detach().cpu().float()
    before = rendered if painted.jpeg is None else _jpeg_round_trip(rendered, painted.jpeg)
    changed = (painted_rgb - before).abs().amax(dim=-1) > tolerance
    changed = torch.from_numpy(_without_small_components(changed.numpy(), MIN_STROKE_PIXELS))
    edit, background = changed.clone(), changed & paint_is_background
    _resolve_seam(changed, before, painted_rgb, target, background, edit, tolerance)
    return EditMasks(edit=edit, background=background & edit, target=target)


def _without_small_components(mask: np.ndarray, min_pixels: int) -> np.ndarray:
    """(H, W) bool `mask` without its 8-connected components of fewer than `min_pixels` pixels."""
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_pixels
    keep[0] = False  # label 0 is the unchanged region
    return keep[labels]


def _resolve_seam(
    changed: torch.Tensor,
    before: torch.Tensor,
    painted: torch.Tensor,
    target: torch.Tensor,
    background: torch.Tensor,
    edit: torch.Tensor,
    tolerance: float,
) -> None:
    """Apply the seam rule in place to `edit`, `background` and `target` (module docstring).

    changed: (H, W) bool; before, painted, target: (H, W, 3) the unedited colour R, the painted colour P and the
    target colours so far (white for background paint)."""
    reach = 2 * SEAM_WIDTH + 1
    kernel = np.ones((reach, reach), np.uint8)
    near_unchanged = torch.from_numpy(cv2.dilate((~changed).numpy().astype(np.uint8), kernel) > 0)
    ys, xs = torch.nonzero(changed & near_unchanged, as_tuple=True)
    if len(ys) == 0:
        return
    offsets = torch.arange(-SEAM_WIDTH, SEAM_WIDTH + 1)
    window_ys = (ys[:, None, None] + offsets[None, :, None]).expand(-1, reach, reach).reshape(len(ys), -1)
    window_xs = (xs[:, None, None] + offsets[None, None, :]).expand(-1, reach, reach).reshape(len(ys), -1)
    height, width = changed.shape
    inside = (window_ys >= 0) & (window_ys < height) & (window_xs >= 0) & (window_xs < width)
    window_ys, window_xs = window_ys.clamp(0, height - 1), window_xs.clamp(0, width - 1)
    candidate = target[window_ys, window_xs]  # (S, K, 3) the colours C each seam pixel may blend
    candidate_is_background = background[window_ys, window_xs]
    moved_far = (painted[ys, xs] - before[ys, xs]).abs().amax(dim=-1) > SEAM_MIN_CHANGE * tolerance
    usable = inside & changed[window_ys, window_xs] & (candidate_is_background | moved_far[:, None])

    start = before[ys, xs][:, None, :]  # (S, 1, 3) R
    offset = painted[ys, xs][:, None, :] - start  # P - R
    direction = candidate - start  # C - R
    squared_length = (direction * direction).sum(dim=-1)
    coverage = ((offset * direction).sum(dim=-1) / squared_length.clamp_min(1e-12)).clamp(0.0, 1.0)
    residual = (offset - coverage[..., None] * direction).abs().amax(dim=-1)
    blends = usable & (residual <= tolerance) & (squared_length > 0)
    purest = torch.where(blends, squared_length, torch.full_like(squared_length, -1.0)).argmax(dim=-1)
    is_blend = blends.any(dim=-1)
    rows = torch.arange(len(ys))
    joins = is_blend & (coverage[rows, purest] >= 0.5)
    drops = is_blend & ~joins

    edit[ys[drops], xs[drops]] = False
    joined_ys, joined_xs, joined_purest = ys[joins], xs[joins], purest[joins]
    target[joined_ys, joined_xs] = candidate[rows[joins], joined_purest]
    background[joined_ys, joined_xs] = candidate_is_background[rows[joins], joined_purest]


def read_user_mask(path: Path | str, shape: tuple[int, int]) -> torch.Tensor:
    """(H, W) bool from the user's --mask image of any mode: in where the luminance, composited on black (so
    transparent pixels are out), is at least 50% grey. shape: (H, W) the edited image's, which the mask must match."""
    path = Path(path)
    height, width = shape
    mask_width, mask_height = image_size(path)  # checked before decoding
    if (mask_height, mask_width) != (height, width):
        raise InputFileError(path, f"the mask is {mask_width}x{mask_height} pixels, the edited image {width}x{height}")
    pixels = read_image(path, "RGBA")
    luminance = pixels[..., :3] @ torch.tensor([0.299, 0.587, 0.114])  # ITU-R 601, as Pillow's "L"
    return luminance * pixels[..., 3] >= 0.5
