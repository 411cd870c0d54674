"""Pictures a person reads: where the video saw the avatar little, and where to look in a suggestion."""

from __future__ import annotations

import io
import math

import cv2
import numpy as np
import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.gaussians import sh_to_rgb
from avatarperfect_cli.refinement.suggest import exposure_relevance
from avatarperfect_cli.refinement.where_to_look import framed_camera, revealing_poses
from avatarperfect_cli.render import Camera, rasterization

PANEL_SIZE = 320  # pixels per view in the visibility picture
GUIDE_TINT = (1.0, 0.0, 0.8)  # magenta: no subject colour is this saturated
GUIDE_OUTLINE = (255, 0, 200)
FONT = cv2.FONT_HERSHEY_SIMPLEX
# The least-seen colour of a pixel is the power mean, this power, of how little its Gaussians were seen,
# weighted by their blend weights: one barely seen Gaussian with a tenth of the weight shows at 56%.
LEAST_SEEN_POWER = 4.0
LUMINANCE = (0.299, 0.587, 0.114)  # Rec. 601 weights of R, G, B
SHADING = 0.3  # share of a pixel's brightness that follows the avatar's own colours (to show its shape)
# Colour stops of "how much the video saw": deep red (barely) -> orange -> pale grey (well seen)
LOOK_STOPS = ((0.0, (0.62, 0.0, 0.16)), (0.35, (0.93, 0.23, 0.10)), (0.65, (1.0, 0.72, 0.25)), (1.0, (0.9, 0.9, 0.9)))


def look_lut() -> torch.Tensor:
    """(256, 3) float32 RGB in [0, 1] of visibility from barely seen (index 0, deep red) to well seen (255,
    pale grey), its lightness rising throughout: the well seen body recedes, the barely seen stands out."""
    positions = np.array([stop for stop, _ in LOOK_STOPS])
    colours = np.array([colour for _, colour in LOOK_STOPS])
    levels = np.linspace(0.0, 1.0, 256)
    return torch.from_numpy(np.stack([np.interp(levels, positions, colours[:, c]) for c in range(3)], axis=1)).float()


# (title, revealing pose, direction from the body to the camera, image up) of each panel; canonical frame
PANELS = (
    ("arms raised, front", "arms raised", (0.0, -0.2, 1.0), (0.0, 1.0, 0.0)),
    ("arms raised, left side", "arms raised", (1.0, -0.2, 0.35), (0.0, 1.0, 0.0)),
    ("legs apart, front, low", "legs apart", (0.0, -0.45, 1.0), (0.0, 1.0, 0.0)),
    ("walking step, left side", "walking step", (1.0, -0.1, 0.0), (0.0, 1.0, 0.0)),
    ("T-pose from below", "T-pose", (0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    ("T-pose from above", "T-pose", (0.0, 1.0, 0.0), (0.0, 0.0, -1.0)),
)


def _text(canvas: np.ndarray, text: str, x: int, baseline_y: int, scale: float = 0.6, centred: bool = True) -> None:
    """Black anti-aliased text centred on (or starting at) `x`, in place on an (H, W, 3) uint8 RGB canvas."""
    width = cv2.getTextSize(text, FONT, scale, 1)[0][0]
    cv2.putText(canvas, text, (x - width // 2 if centred else x, baseline_y), FONT, scale, (0, 0, 0), 1, cv2.LINE_AA)


def _colour_bar(lut: torch.Tensor, low: float, high: float, height: int, label: str) -> np.ndarray:
    """(height, w, 3) uint8 RGB: a vertical colour bar of `lut` from `low` (bottom) to `high` (top) on a
    log scale, ticks at the powers of ten between them, and `label` written upwards beside it."""
    bar_width, margin, label_width = 18, int(0.05 * height), 44
    canvas = np.full((height, bar_width + label_width + 24, 3), 255, np.uint8)
    top, bottom = margin, height - margin
    rows = torch.linspace(1.0, 0.0, bottom - top)
    canvas[top:bottom, :bar_width] = (lut[(rows * 255).round().long()] * 255).round().byte().numpy()[:, None]
    cv2.rectangle(canvas, (0, top), (bar_width - 1, bottom - 1), (0, 0, 0), 1)
    log_low, log_high = math.log10(low), math.log10(high)
    for power in range(math.ceil(log_low), math.floor(log_high) + 1):
        y = round(bottom - 1 - (power - log_low) / (log_high - log_low) * (bottom - top - 1))
        cv2.line(canvas, (bar_width, y), (bar_width + 4, y), (0, 0, 0), 1)
        cv2.putText(canvas, f"1e{power}", (bar_width + 7, y + 5), FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    strip = np.full((24, height, 3), 255, np.uint8)  # the label, written along the bar, then turned
    _text(strip, label, height // 2, 17, 0.5)
    canvas[:, -24:] = np.rot90(strip)
    return canvas


def _region_list(shares: list[tuple[str, float, int]], height: int) -> np.ndarray:
    """(height, w, 3) uint8 RGB: the body regions, most barely seen first, with their shares."""
    canvas = np.full((height, 250, 3), 255, np.uint8)
    _text(canvas, "barely seen Gaussians", 8, 30, 0.55, centred=False)
    _text(canvas, "by region (check first):", 8, 52, 0.55, centred=False)
    for row, (name, share, _) in enumerate(shares):
        _text(canvas, f"{100 * share:5.1f}%  {name}", 8, 88 + 26 * row, 0.55, centred=False)
    return canvas


def least_seen_shade(
    avatar: Avatar, body_pose: torch.Tensor, camera: Camera, shade: torch.Tensor, power: float = LEAST_SEEN_POWER
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The avatar in `body_pose` (24, 3) seen by `camera`, each pixel shaded by the least seen Gaussians that
    contribute to it. shade: (N,) in [0, 1], 0 = barely seen. Returns the pixels' shade (H, W) in [0, 1]:
    1 - (sum_i w_i (1 - shade_i)^power / sum_i w_i)^(1 / power) with w_i = T_i alpha_i, so a barely seen
    Gaussian under well seen ones still darkens the pixel; the luminance of the avatar's own colours (H, W)
    in [0, 1]; alpha (H, W). On the CPU."""
    with torch.no_grad():
        means, quats = avatar.pose(body_pose, torch.zeros(3))
        colours = sh_to_rgb(avatar.params["sh_dc"][:, 0]).clamp(0, 1)  # view-independent: shape, not shine
        luminance = colours @ torch.tensor(LUMINANCE, dtype=colours.dtype, device=colours.device)
        features = torch.stack([(1.0 - shade.to(means)) ** power, luminance], dim=1)
        out = rasterization(means, quats, avatar.scales, avatar.opacities, features, camera)
    alpha = out.alpha.cpu()
    coverage = alpha.clamp_min(1e-6)
    least = 1.0 - (out.image[..., 0].cpu() / coverage).clamp(0, 1) ** (1.0 / power)
    return torch.where(alpha > 1e-3, least, 1.0), (out.image[..., 1].cpu() / coverage).clamp(0, 1), alpha


def visibility_picture(
    avatar: Avatar, visibility: torch.Tensor, exposure: torch.Tensor, shares: list[tuple[str, float, int]], title: str
) -> bytes:
    """PNG bytes: the avatar in poses that open the armpits, the crotch and the inner arms, and from below
    and above, each pixel coloured by the least seen Gaussians in it (`least_seen_shade`) on a logarithmic
    scale of the accumulated visibility V (N,) from a hundredth of its mean (red: barely seen) to its mean
    (pale grey), with a colour bar and the body regions' shares of barely seen Gaussians (`shares`, most
    first). A Gaussian counts as much as the revealing poses show it (`exposure` (N,), `exposure_relevance`):
    the inside of the body never shows and stays out of the colours. Rendered on the avatar's device;
    `visibility` and `exposure` on the CPU."""
    high = max(float(visibility.mean()), 1e-12)
    low = 0.01 * high
    seen = (visibility.clamp(low, high).log() - math.log(low)) / (math.log(high) - math.log(low))
    shade = 1.0 - (1.0 - seen) * exposure_relevance(exposure.double())
    lut = look_lut()
    poses = revealing_poses()
    panels = []
    for _, pose_name, direction, up in PANELS:
        body_pose = poses[pose_name]
        with torch.no_grad():
            means, _ = avatar.pose(body_pose, torch.zeros(3))
        camera = framed_camera(means.cpu(), direction, up, PANEL_SIZE)
        least, luminance, alpha = least_seen_shade(avatar, body_pose, camera.to(avatar.device), shade)
        colour = lut[(least * 255).round().long()] * (1.0 - SHADING + SHADING * luminance[..., None])
        image = alpha[..., None] * colour + (1.0 - alpha[..., None])
        panels.append((image.clamp(0, 1) * 255).round().byte().numpy())
    title_height, name_height, columns = 40, 28, 3
    rows = [np.concatenate(panels[start : start + columns], axis=1) for start in range(0, len(panels), columns)]
    row_height = name_height + PANEL_SIZE
    body = np.full((row_height * len(rows), columns * PANEL_SIZE, 3), 255, np.uint8)
    for index, row in enumerate(rows):
        body[index * row_height + name_height : (index + 1) * row_height] = row
    for index, (name, _, _, _) in enumerate(PANELS):
        row, column = divmod(index, columns)
        _text(body, name, column * PANEL_SIZE + PANEL_SIZE // 2, row * row_height + 20)
    bar = _colour_bar(lut, low, high, body.shape[0], "mean visibility per frame (pixels)")
    listing = _region_list(shares, body.shape[0])
    canvas = np.full((title_height + body.shape[0], body.shape[1] + bar.shape[1] + listing.shape[1], 3), 255, np.uint8)
    canvas[title_height:] = np.concatenate([body, bar, listing], axis=1)
    _text(canvas, title, canvas.shape[1] // 2, 28, 0.7)
    return cv2.imencode(".png", canvas[..., ::-1])[1].tobytes()


def figure_png(figure, title: str) -> bytes:
    """PNG bytes of a matplotlib figure with `title`, laid out tightly; the figure is closed."""
    from matplotlib import pyplot as plt

    figure.suptitle(title)
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=100)
    plt.close(figure)
    return buffer.getvalue()


def labelled_grid(rows: list[list[torch.Tensor | None]], row_labels: list[str], column_labels: list[str]):
    """A matplotlib figure of images in a grid: `column_labels` above the first row, `row_labels` left of each row.

    rows: per row, one (H, W, 3) image in [0, 1] per column, or None for an empty panel ("not yet")."""
    from matplotlib import pyplot as plt

    height, width = next(image.shape[:2] for row in rows for image in row if image is not None)
    panel = 2.2  # inches per panel side at the wider of H and W
    size = (panel * width / max(height, width), panel * height / max(height, width))
    figsize = (size[0] * len(column_labels) + 1.2, size[1] * len(rows) + 0.8)
    figure, axes = plt.subplots(len(rows), len(column_labels), figsize=figsize, squeeze=False)
    for r, (row, label) in enumerate(zip(rows, row_labels)):
        for c, image in enumerate(row):
            axis = axes[r, c]
            axis.set_xticks([])
            axis.set_yticks([])
            if image is None:
                axis.text(0.5, 0.5, "not yet", ha="center", va="center", color="grey", transform=axis.transAxes)
            else:
                axis.imshow(image.clamp(0, 1).numpy(), interpolation="nearest")
            if r == 0:
                axis.set_title(column_labels[c], fontsize=11)
        axes[r, 0].set_ylabel(label, fontsize=11)
    return figure


def caption_strip(labels: list[str], panel_width: int) -> torch.Tensor:
    """(h, len(labels) * panel_width, 3) in [0, 1]: white, each label centred above its panel, the text as large
    as the widest label allows (at most 0.8) and h to match, so small videos keep readable captions."""
    widest = max(cv2.getTextSize(label, FONT, 1.0, 1)[0][0] for label in labels)
    scale = min(0.8, 0.92 * panel_width / max(widest, 1))
    height = 2 * round(14 * scale / 0.6 + 2)  # even: video encoders want even sides
    canvas = np.full((height, len(labels) * panel_width, 3), 255, np.uint8)
    for index, label in enumerate(labels):
        _text(canvas, label, index * panel_width + panel_width // 2, int(height * 0.7), scale)
    return torch.from_numpy(canvas.astype(np.float32) / 255.0)


def guide_image(image: torch.Tensor, dominated: torch.Tensor) -> torch.Tensor:
    """(H, W, 3) the suggested image with the pixels dominated by barely-seen Gaussians tinted and outlined.

    image: (H, W, 3) in [0, 1]; dominated: (H, W) bool.
    """
    tint = torch.tensor(GUIDE_TINT)
    guide = torch.where(dominated[..., None], 0.55 * image + 0.45 * tint, image)
    pixels = np.ascontiguousarray((guide.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8))
    mask = dominated.numpy().astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    thickness = max(1, math.ceil(max(image.shape[:2]) / 300))
    cv2.drawContours(pixels, contours, -1, GUIDE_OUTLINE, thickness, lineType=cv2.LINE_AA)
    return torch.from_numpy(pixels.astype(np.float32) / 255.0)
