import struct
import zlib
from collections import deque
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from PIL import Image, ImageCms

from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.io.images import write_image
from avatarperfect_cli.refinement.edit_image import (
    DEFAULT_TOLERANCE,
    LOSSY_TOLERANCE,
    SEAM_MIN_CHANGE,
    SEAM_WIDTH,
    PaintedImage,
    derive_edit_masks,
    read_painted_image,
    read_user_mask,
)

HEIGHT, WIDTH = 24, 32
GREEN = np.array([40, 200, 60]) / 255.0


# ---------------------------------------------------------------- files an editor saves


def painted_content() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(palette indices (H, W), palette (12, 3) uint8, stroke (H, W) bool): 4x4 blocks of 12 colours and a
    3-px stroke that is painted white, or erased to transparency, depending on the file kind."""
    rng = np.random.default_rng(1)
    palette = rng.integers(0, 240, (12, 3)).astype(np.uint8)
    indices = np.kron(rng.integers(0, 12, (HEIGHT // 4, WIDTH // 4)), np.ones((4, 4), np.int64))
    stroke = np.zeros((HEIGHT, WIDTH), np.uint8)
    cv2.line(stroke, (3, 4), (27, 19), 1, 3)
    return indices, palette, stroke.astype(bool)


def grey(rgb: np.ndarray) -> np.ndarray:
    return np.asarray(Image.fromarray(rgb).convert("L"))


def png_bytes(pixels: np.ndarray, colour_type: int) -> bytes:
    """A 16-bit PNG written by hand (for layouts neither Pillow nor OpenCV writes): pixels (H, W, C) uint16."""
    height, width = pixels.shape[:2]
    rows = b"".join(b"\x00" + pixels[y].astype(">u2").tobytes() for y in range(height))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 16, colour_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b"")


def swapped_primaries_profile() -> bytes:
    """An RGB ICC profile that is sRGB with the red and green primaries exchanged (and not named sRGB): its first
    channel is sRGB's green, so converting it to sRGB swaps the channels back."""
    profile = bytearray(ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes())
    entries = {}
    for index in range(struct.unpack(">I", profile[128:132])[0]):
        start = 132 + 12 * index
        entries[bytes(profile[start : start + 4])] = start
    red, green = entries[b"rXYZ"], entries[b"gXYZ"]
    profile[red + 4 : red + 12], profile[green + 4 : green + 12] = (
        profile[green + 4 : green + 12],
        profile[red + 4 : red + 12],
    )
    name = bytes(profile).index("sRGB".encode("utf-16-be"))
    profile[name : name + 8] = "xRGB".encode("utf-16-be")
    return bytes(profile)


def write_kind(path: Path, kind: str) -> tuple[np.ndarray, bool]:
    """Write the painted content as `kind`; (the rgb uint8 (H, W, 3) it should read as, whether the stroke is
    transparent rather than white)."""
    indices, palette, stroke = painted_content()
    colour = palette[indices]
    white = np.where(stroke[..., None], 255, colour).astype(np.uint8)
    alpha = np.where(stroke, 0, 255).astype(np.uint8)
    erased = np.where(stroke[..., None], 0, colour).astype(np.uint8)  # erasers keep (or zero) the colour under alpha 0
    grey_white, grey_erased = grey(white), grey(erased)
    srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    if kind == "RGB":
        Image.fromarray(white).save(path)
    elif kind == "RGBA":
        Image.fromarray(np.dstack([erased, alpha])).save(path)
    elif kind == "L":
        Image.fromarray(grey_white).save(path)
    elif kind == "LA":
        Image.fromarray(np.dstack([grey_erased, alpha]), "LA").save(path)
    elif kind in ("P", "P+tRNS"):
        image = Image.fromarray(np.where(stroke, 12, indices).astype(np.uint8), "P")
        image.putpalette(np.concatenate([palette, [[255, 255, 255]]]).ravel().tolist())
        image.save(path, **({"transparency": 12} if kind == "P+tRNS" else {}))
    elif kind == "RGB 16-bit":
        cv2.imwrite(str(path), white[..., ::-1].astype(np.uint16) * 257)
    elif kind == "RGBA 16-bit":
        cv2.imwrite(str(path), np.dstack([erased[..., ::-1], alpha]).astype(np.uint16) * 257)
    elif kind == "LA 16-bit":
        path.write_bytes(png_bytes(np.dstack([grey_erased, alpha]).astype(np.uint16) * 257, colour_type=4))
    elif kind == "I;16":
        cv2.imwrite(str(path), grey_white.astype(np.uint16) * 257)
    elif kind == "sRGB ICC":
        Image.fromarray(white).save(path, icc_profile=srgb)
    elif kind == "other ICC":
        Image.fromarray(white[..., [1, 0, 2]]).save(path, icc_profile=swapped_primaries_profile())
    elif kind == "JPEG":
        Image.fromarray(white).save(path, quality=95, subsampling=0)
    greys = kind in ("L", "LA", "LA 16-bit", "I;16")
    expected = np.repeat(grey_white[..., None], 3, axis=-1) if greys else white
    return expected, kind in ("RGBA", "LA", "P+tRNS", "RGBA 16-bit", "LA 16-bit")


KINDS = [
    "RGB",
    "RGBA",
    "L",
    "LA",
    "P",
    "P+tRNS",
    "RGB 16-bit",
    "RGBA 16-bit",
    "LA 16-bit",
    "I;16",
    "sRGB ICC",
    "other ICC",
]


@pytest.mark.parametrize("kind", KINDS + ["JPEG"])
def test_every_file_kind_reads_the_same_painting(tmp_path: Path, kind: str) -> None:
    path = tmp_path / ("painted.jpg" if kind == "JPEG" else "painted.png")
    expected, transparent_stroke = write_kind(path, kind)
    painted = read_painted_image(path)
    _, _, stroke = painted_content()
    assert painted.rgb.dtype == torch.float32 and painted.rgb.shape == (HEIGHT, WIDTH, 3)
    error = (painted.rgb.double() * 255.0 - torch.from_numpy(expected).double()).abs().max()
    assert error <= (LOSSY_TOLERANCE * 255.0 if kind == "JPEG" else 1.0)
    assert torch.equal(
        painted.transparent, torch.from_numpy(stroke) if transparent_stroke else torch.zeros_like(painted.transparent)
    )
    assert painted.lossy == (kind == "JPEG") and (painted.jpeg is not None) == (kind == "JPEG")


@pytest.mark.parametrize("layout", ["RGB", "RGBA", "LA", "I;16"])
def test_sixteen_bit_pngs_keep_their_precision(tmp_path: Path, layout: str) -> None:
    rng = np.random.default_rng(2)
    channels = {"RGB": 3, "RGBA": 4, "LA": 2, "I;16": 1}[layout]
    values = rng.integers(0, 65536, (HEIGHT, WIDTH, channels)).astype(np.uint16)
    values[..., -1] = np.where(values[..., -1] < 32768, 0, 65535) if layout in ("RGBA", "LA") else values[..., -1]
    path = tmp_path / "painted.png"
    if layout == "LA":
        path.write_bytes(png_bytes(values, colour_type=4))
    else:
        cv2.imwrite(str(path), values[..., [2, 1, 0, 3][:channels]] if channels > 1 else values[..., 0])
    colour = values[..., :3] if channels >= 3 else np.repeat(values[..., :1], 3, axis=-1)
    alpha = values[..., -1:] / 65535.0 if layout in ("RGBA", "LA") else np.ones((HEIGHT, WIDTH, 1))
    expected = colour / 65535.0 * alpha + (1.0 - alpha)  # composited on white
    painted = read_painted_image(path)
    assert np.abs(painted.rgb.double().numpy() - expected).max() < 1e-6  # 8 bits would be off by up to 1/255
    assert torch.equal(painted.transparent, torch.from_numpy(alpha[..., 0] < 0.5))


def test_partly_transparent_pixels_composite_on_white(tmp_path: Path) -> None:
    rgba = np.zeros((2, 3, 4), np.uint8)
    rgba[..., 0] = 200
    rgba[..., 3] = [[0, 64, 127], [128, 200, 255]]
    Image.fromarray(rgba).save(tmp_path / "a.png")
    painted = read_painted_image(tmp_path / "a.png")
    alpha = rgba[..., 3] / 255.0
    expected = np.stack([200 / 255.0 * alpha + 1 - alpha, 1 - alpha, 1 - alpha], axis=-1)
    assert np.abs(painted.rgb.numpy() - expected).max() < 1e-6
    assert painted.transparent.tolist() == [[True, True, True], [False, False, False]]


def assert_one_line_naming(error: pytest.ExceptionInfo, path: Path) -> None:
    message = str(error.value)
    assert "\n" not in message and str(path) in message


def test_unreadable_files_are_one_line_errors(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    noise = rng.integers(0, 256, (64, 64, 3)).astype(np.uint8)
    cases = {}
    Image.fromarray(noise).save(tmp_path / "full.png")
    cases["truncated.png"] = (tmp_path / "full.png").read_bytes()[:6000]
    cv2.imwrite(str(tmp_path / "full16.png"), noise.astype(np.uint16) * 257)
    cases["truncated16.png"] = (tmp_path / "full16.png").read_bytes()[:9000]
    cases["notes.png"] = b"not an image at all\n"
    cases["empty.png"] = png_bytes(np.zeros((0, 5, 3), np.uint16), colour_type=2)
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
    Image.fromarray(np.arange(12, dtype=np.int32).reshape(3, 4)).save(tmp_path / "int32.tif")
    for name in [*cases, "int32.tif", "missing.png"]:
        with pytest.raises(InputFileError) as error:
            read_painted_image(tmp_path / name)
        assert_one_line_naming(error, tmp_path / name)


# ---------------------------------------------------------------- the edit masks


def synthetic_render(height: int, width: int) -> np.ndarray:
    """(H, W, 3) float64 on 8-bit levels: a textured ellipse (anti-aliased edge) on white, like suggested.png."""
    ys, xs = np.mgrid[0:height, 0:width]
    body = np.zeros((height, width), np.uint8)
    cv2.ellipse(body, (width // 2, height // 2), (width * 2 // 5, height * 2 // 5), 0, 0, 360, 255, -1, cv2.LINE_AA)
    coverage = body[..., None] / 255.0
    texture = np.stack(
        [0.3 + 0.2 * np.sin(xs / 7.0), 0.25 + 0.15 * np.cos(ys / 5.0), 0.35 + 0.1 * np.sin((xs + ys) / 9.0)], -1
    )
    return np.round((texture * coverage + 1.0 - coverage) * 255.0) / 255.0


def stroke_coverage(
    height: int, width: int, start: tuple[int, int], end: tuple[int, int], thickness: int
) -> np.ndarray:
    """(H, W) float64 in [0, 1]: an anti-aliased brush stroke's coverage."""
    mask = np.zeros((height, width), np.uint8)
    cv2.line(mask, start, end, 255, thickness, cv2.LINE_AA)
    return mask / 255.0


def paint(render: np.ndarray, strokes: list[tuple[np.ndarray, np.ndarray]], noise_levels: int, seed: int) -> np.ndarray:
    """Blend each (coverage, colour) stroke over the render as an editor does, add ±noise_levels of noise to every
    pixel, and quantise to 8 bits."""
    painted = render.copy()
    for coverage, colour in strokes:
        painted = painted * (1.0 - coverage[..., None]) + colour * coverage[..., None]
    noise = np.random.default_rng(seed).integers(-noise_levels, noise_levels + 1, painted.shape)
    return np.clip(np.round(painted * 255.0) + noise, 0, 255) / 255.0


def as_painted(rgb: np.ndarray, transparent: np.ndarray | None = None) -> PaintedImage:
    clear = np.zeros(rgb.shape[:2], bool) if transparent is None else transparent
    return PaintedImage(torch.tensor(rgb, dtype=torch.float32), torch.from_numpy(clear), lossy=False)


def two_strokes(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(white stroke coverage, green stroke coverage), disjoint, both crossing the body."""
    white = stroke_coverage(height, width, (width // 6, height // 3), (width // 2, height * 2 // 3), 9)
    green = stroke_coverage(height, width, (width * 5 // 8, height // 4), (width * 7 // 8, height * 3 // 4), 7)
    assert not ((white > 0) & (green > 0)).any()
    return white, green


def test_strokes_give_edit_background_and_pure_targets() -> None:
    height, width = 96, 128
    render = synthetic_render(height, width)
    white, green = two_strokes(height, width)
    painted = paint(render, [(white, np.ones(3)), (green, GREEN)], noise_levels=3, seed=0)
    masks = derive_edit_masks(as_painted(painted), torch.tensor(render, dtype=torch.float32))
    edit, background, target = masks.edit.numpy(), masks.background.numpy(), masks.target.numpy()
    on_body = np.abs(1.0 - render).max(axis=-1) > 0.2  # where white paint is a visible change

    is_paint = np.abs(target - GREEN).max(axis=-1) <= 3.0 / 255.0 + 1e-6  # ± the noise
    is_faint = np.abs(target - render).max(axis=-1) <= SEAM_MIN_CHANGE * DEFAULT_TOLERANCE + 1e-6  # a few % paint
    mostly_render = np.maximum(white, green) <= 0.4
    assert not edit[mostly_render & (green == 0)].any()  # noise, and a white stroke's seam, are no edit
    assert is_faint[edit & mostly_render].all()  # the green seam only where it is hardly paint
    assert edit[(green >= 0.6) | ((white >= 0.6) & on_body)].all()
    assert background[(white >= 0.6) & on_body].all() and not background[white < 0.4].any()
    assert not (background & ~edit).any()
    colour = edit & ~background
    assert colour.any() and (is_paint | is_faint)[colour].all() and is_paint[colour].mean() > 0.9
    assert not colour[white > 0].any()  # no pixel of the white stroke, seam included, is a colour target
    assert (target[background] == 1.0).all()
    assert masks.counts() == {
        "edited": int(edit.sum()),
        "background": int(background.sum()),
        "colour": int(colour.sum()),
    }


@pytest.mark.parametrize("levels", [6, 8])
def test_noise_of_three_levels_is_no_edit_and_a_shifted_block_is(levels: int) -> None:
    render = synthetic_render(40, 56)
    quiet = paint(render, [], noise_levels=3, seed=1)
    assert not derive_edit_masks(as_painted(quiet), torch.tensor(render, dtype=torch.float32)).edit.any()
    shifted = render.copy()
    shifted[10:20, 20:30] = np.clip(shifted[10:20, 20:30] + np.array([levels, -levels, levels]) / 255.0, 0, 1)
    masks = derive_edit_masks(as_painted(shifted), torch.tensor(render, dtype=torch.float32))
    block = np.zeros((40, 56), bool)
    block[10:20, 20:30] = True
    assert np.array_equal(masks.edit.numpy(), block)
    assert torch.equal(masks.target[masks.edit], torch.tensor(shifted, dtype=torch.float32)[masks.edit])


def test_erasing_to_transparency_is_background_and_its_seam_no_colour() -> None:
    height, width = 48, 64
    render = synthetic_render(height, width)
    stroke = stroke_coverage(height, width, (10, 10), (50, 40), 7)  # the eraser: alpha = 1 - stroke
    composited = np.round((1.0 - (1.0 - stroke[..., None]) * (1.0 - render)) * 255.0) / 255.0  # on white, as read
    erased = stroke > 0.5  # alpha < 0.5
    masks = derive_edit_masks(as_painted(composited, erased), torch.tensor(render, dtype=torch.float32))
    changed = np.abs(composited - render).max(axis=-1) > DEFAULT_TOLERANCE
    assert (erased & changed).sum() > 100
    assert np.array_equal(masks.background.numpy(), erased & changed)
    assert torch.equal(masks.edit, masks.background)  # the lightened seam (alpha >= 0.5) is dropped, not a colour
    assert (masks.target[masks.background] == 1.0).all()


def reference_masks(
    painted: np.ndarray, render: np.ndarray, clear: np.ndarray, tolerance: float
) -> tuple[np.ndarray, ...]:
    """The documented rules, pixel by pixel in float64: (edit, background, target, ambiguous), where ambiguous marks
    pixels whose outcome hangs on a comparison within 1e-5 of its threshold (float32 may decide those otherwise)."""
    height, width = render.shape[:2]
    changed = np.abs(painted - render).max(axis=-1) > tolerance
    seen = np.zeros_like(changed)
    for y, x in np.argwhere(changed):
        if seen[y, x]:
            continue
        component, queue = [], deque([(y, x)])
        seen[y, x] = True
        while queue:
            cy, cx = queue.popleft()
            component.append((cy, cx))
            for ny in range(max(cy - 1, 0), min(cy + 2, height)):
                for nx in range(max(cx - 1, 0), min(cx + 2, width)):
                    if changed[ny, nx] and not seen[ny, nx]:
                        seen[ny, nx] = True
                        queue.append((ny, nx))
        if len(component) < 3:
            for cy, cx in component:
                changed[cy, cx] = False
    paint_is_background = clear | (painted >= 1.0 - tolerance).all(axis=-1)
    first_target = np.where(paint_is_background[..., None], 1.0, painted)
    edit, background, target = changed.copy(), changed & paint_is_background, first_target.copy()
    ambiguous = np.zeros_like(changed)
    for y, x in np.argwhere(changed):
        window = [
            (y + dy, x + dx)
            for dy in range(-SEAM_WIDTH, SEAM_WIDTH + 1)
            for dx in range(-SEAM_WIDTH, SEAM_WIDTH + 1)
            if 0 <= y + dy < height and 0 <= x + dx < width
        ]
        if all(changed[wy, wx] for wy, wx in window):
            continue
        best = None
        moved = np.abs(painted[y, x] - render[y, x]).max()
        ambiguous[y, x] |= abs(moved - SEAM_MIN_CHANGE * tolerance) < 1e-5
        for wy, wx in window:
            if not changed[wy, wx] or not (paint_is_background[wy, wx] or moved > SEAM_MIN_CHANGE * tolerance):
                continue
            direction = first_target[wy, wx] - render[y, x]
            length = direction @ direction
            if length == 0:
                continue
            share = (painted[y, x] - render[y, x]) @ direction / length
            coverage = min(max(share, 0.0), 1.0)
            residual = np.abs(painted[y, x] - render[y, x] - coverage * direction).max()
            ambiguous[y, x] |= abs(residual - tolerance) < 1e-5
            if residual > tolerance:
                continue
            if best is not None and abs(length - best[0]) < 1e-9:  # a tie: harmless when both mean the same
                same = np.array_equal(first_target[wy, wx], best[2]) and paint_is_background[wy, wx] == best[3]
                ambiguous[y, x] |= not same
            if best is None or length > best[0]:
                best = (length, coverage, first_target[wy, wx], paint_is_background[wy, wx])
        if best is not None:
            ambiguous[y, x] |= abs(best[1] - 0.5) < 1e-5
            if best[1] >= 0.5:
                target[y, x], background[y, x] = best[2], best[3]
            else:
                edit[y, x] = background[y, x] = False
    return edit, background, target, ambiguous


def test_matches_a_pixel_by_pixel_reference() -> None:
    height, width = 40, 56
    render = synthetic_render(height, width)
    white, green = two_strokes(height, width)
    thin = stroke_coverage(height, width, (4, 36), (50, 34), 1)  # a thin red line: no pure paint inside
    strokes = [(white, np.ones(3)), (green, GREEN), (thin * (white == 0) * (green == 0), np.array([0.9, 0.1, 0.1]))]
    painted = paint(render, strokes, noise_levels=3, seed=4)
    painted[2, 2] = painted[30, 5] = painted[31, 6] = 0.0  # speckles of 1 and 2 pixels
    painted[5, 50:53] = 0.0  # three pixels: a stroke
    clear = np.zeros((height, width), bool)
    clear[28:31, 12:17] = True
    painted[clear] = 1.0
    masks = derive_edit_masks(as_painted(painted, clear), torch.tensor(render, dtype=torch.float32))
    edit, background, target, ambiguous = reference_masks(painted, render, clear, DEFAULT_TOLERANCE)
    decided = ~ambiguous
    assert ambiguous.mean() < 0.01
    assert not edit[2, 2] and not edit[30, 5] and edit[5, 50:53].all() and background[28:31, 12:17].all()
    assert np.array_equal(masks.edit.numpy()[decided], edit[decided])
    assert np.array_equal(masks.background.numpy()[decided], background[decided])
    inside = decided & edit
    assert np.abs(masks.target.numpy()[inside] - target[inside]).max() < 1e-6


def test_user_mask_replaces_the_difference() -> None:
    height, width = 32, 40
    render = synthetic_render(height, width)
    painted = render.copy()
    painted[8:16, 8:16] = 1.0  # white: background
    painted[8:16, 20:28] = GREEN
    user_mask = np.zeros((height, width), bool)
    user_mask[6:18, 6:30] = True  # also holds unchanged pixels, and leaves none out
    masks = derive_edit_masks(
        as_painted(painted), torch.tensor(render, dtype=torch.float32), user_mask=torch.from_numpy(user_mask)
    )
    assert np.array_equal(masks.edit.numpy(), user_mask)
    white = (painted >= 1.0 - DEFAULT_TOLERANCE).all(axis=-1)
    assert np.array_equal(masks.background.numpy(), user_mask & white)
    expected_target = np.where(white[..., None], 1.0, painted)
    assert np.abs(masks.target.numpy()[user_mask] - expected_target[user_mask]).max() < 1e-6
    with pytest.raises(AvatarPerfectError):
        derive_edit_masks(
            as_painted(painted), torch.tensor(render, dtype=torch.float32), user_mask=torch.ones(3, 3, dtype=torch.bool)
        )


def test_render_of_another_size_is_an_error() -> None:
    render = synthetic_render(32, 40)
    with pytest.raises(AvatarPerfectError, match="40x32"):
        derive_edit_masks(as_painted(render), torch.zeros(30, 40, 3))


def striped_render(height: int, width: int) -> np.ndarray:
    """(H, W, 3) float64 on 8-bit levels: an ellipse of saturated red and blue stripes on white, whose chroma
    edges JPEG's 4:2:0 subsampling smears by tens of levels."""
    xs = np.arange(width)[None, :, None]
    stripes = np.where((xs // 6) % 2 == 0, np.array([200, 30, 40]) / 255.0, np.array([30, 60, 200]) / 255.0)
    body = np.zeros((height, width), np.uint8)
    cv2.ellipse(body, (width // 2, height // 2), (width * 2 // 5, height * 2 // 5), 0, 0, 360, 255, -1, cv2.LINE_AA)
    coverage = body[..., None] / 255.0
    return np.round((stripes * coverage + 1.0 - coverage) * 255.0) / 255.0


def test_jpeg_edit_is_compared_with_the_render_compressed_alike(tmp_path: Path) -> None:
    height, width = 128, 160
    render = striped_render(height, width)
    white, green = two_strokes(height, width)
    painted = paint(render, [(white, np.ones(3)), (green, GREEN)], noise_levels=0, seed=0)
    Image.fromarray(np.round(painted * 255).astype(np.uint8)).save(tmp_path / "edited.jpg", quality=90)  # 4:2:0
    edited = read_painted_image(tmp_path / "edited.jpg")
    masks = derive_edit_masks(edited, torch.tensor(render, dtype=torch.float32))
    painted_anywhere = cv2.dilate((np.maximum(white, green) > 0).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    on_body = np.abs(1.0 - render).max(axis=-1) > 0.2
    assert edited.lossy and edited.jpeg is not None
    assert masks.edit.numpy()[(green >= 0.75) | ((white >= 0.75) & on_body)].mean() > 0.99
    assert masks.edit.numpy()[~painted_anywhere].sum() <= 10  # ringing next to the strokes only, never far away
    raw = derive_edit_masks(
        PaintedImage(edited.rgb, edited.transparent, lossy=True), torch.tensor(render, dtype=torch.float32)
    )
    assert raw.edit.numpy()[~painted_anywhere].sum() > 10 * max(masks.edit.numpy()[~painted_anywhere].sum(), 1)


# ---------------------------------------------------------------- the user's mask


def test_user_mask_threshold_alpha_and_modes(tmp_path: Path) -> None:
    levels = np.array([[0, 127, 128, 255]], np.uint8)
    Image.fromarray(levels).save(tmp_path / "grey.png")
    assert read_user_mask(tmp_path / "grey.png", (1, 4)).tolist() == [[False, False, True, True]]
    rgba = np.array([[[255, 255, 255, 0], [255, 255, 255, 255], [0, 0, 0, 255], [255, 255, 255, 200]]], np.uint8)
    Image.fromarray(rgba).save(tmp_path / "layer.png")
    assert read_user_mask(tmp_path / "layer.png", (1, 4)).tolist() == [[False, True, False, True]]
    cv2.imwrite(str(tmp_path / "deep.png"), np.array([[0, 32767, 32896, 65535]], np.uint16))
    assert read_user_mask(tmp_path / "deep.png", (1, 4)).tolist() == [[False, False, True, True]]
    write_image(tmp_path / "colour.png", torch.tensor([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]]))
    assert read_user_mask(tmp_path / "colour.png", (1, 2)).tolist() == [[False, True]]  # luminance 0.30, 0.59


def test_user_mask_of_another_size_is_a_one_line_error(tmp_path: Path) -> None:
    Image.fromarray(np.zeros((4, 5), np.uint8)).save(tmp_path / "mask.png")
    with pytest.raises(InputFileError, match="5x4") as error:
        read_user_mask(tmp_path / "mask.png", (4, 6))
    assert_one_line_naming(error, tmp_path / "mask.png")
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    with pytest.raises(InputFileError):
        read_user_mask(tmp_path / "broken.png", (4, 5))
