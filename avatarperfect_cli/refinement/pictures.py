"""Pictures a person reads: where the video saw the avatar little, and where to look in a suggestion."""

from __future__ import annotations

import io
import math

import cv2
import numpy as np
import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.body import NUM_JOINTS
from avatarperfect_cli.render import Camera, look_at, rasterization
from avatarperfect_cli.render.camera import framing_distance

PANEL_SIZE = 320  # pixels per view in the visibility picture
# (name, direction from the body to the camera, image up), canonical frame: +Y up, +Z the body's front
CANONICAL_VIEWS = (
    ("front", (0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
    ("left side", (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
    ("back", (0.0, 0.0, -1.0), (0.0, 1.0, 0.0)),
    ("right side", (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
    ("below", (0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
)
GUIDE_TINT = (1.0, 0.0, 0.8)  # magenta: no subject colour is this saturated
GUIDE_OUTLINE = (255, 0, 200)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def barely_seen(visibility: torch.Tensor, share_of_mean: float = 0.1) -> torch.Tensor:
    """(N,) bool: Gaussians the video saw less than `share_of_mean` of the mean visibility."""
    return visibility < share_of_mean * visibility.mean()


def _panel_camera(points: torch.Tensor, direction: tuple[float, ...], up: tuple[float, ...]) -> Camera:
    center = 0.5 * (points.min(dim=0).values + points.max(dim=0).values)
    focal = 2.5 * PANEL_SIZE
    K = torch.tensor([[focal, 0.0, PANEL_SIZE / 2], [0.0, focal, PANEL_SIZE / 2], [0.0, 0.0, 1.0]])
    towards = torch.tensor(direction)
    rotation = look_at(center + towards, center, torch.tensor(up))[:3, :3]
    distance = float(framing_distance(points - center, rotation, K, PANEL_SIZE, PANEL_SIZE, fill=0.92))
    return Camera(K, look_at(center + distance * towards, center, torch.tensor(up)), PANEL_SIZE, PANEL_SIZE)


def viridis_lut() -> torch.Tensor:
    """(256, 3) float32 RGB in [0, 1]: the perceptual viridis colour map (OpenCV's table)."""
    levels = np.arange(256, dtype=np.uint8)[:, None]
    bgr = cv2.applyColorMap(levels, cv2.COLORMAP_VIRIDIS)[:, 0]
    return torch.from_numpy(np.ascontiguousarray(bgr[:, ::-1])).float() / 255.0


def _text(canvas: np.ndarray, text: str, center_x: int, baseline_y: int, scale: float = 0.6) -> None:
    """Black anti-aliased text centred on `center_x`, in place on an (H, W, 3) uint8 RGB canvas."""
    width = cv2.getTextSize(text, FONT, scale, 1)[0][0]
    cv2.putText(canvas, text, (center_x - width // 2, baseline_y), FONT, scale, (0, 0, 0), 1, cv2.LINE_AA)


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


def visibility_picture(avatar: Avatar, visibility: torch.Tensor, title: str) -> bytes:
    """PNG bytes: the canonical avatar (T-pose) from the front, both sides, the back and below, each
    Gaussian coloured by its accumulated visibility V (N,) on a logarithmic perceptual colour map
    (dark: barely seen), with a colour bar. Rendered on the avatar's device; `visibility` on the CPU."""
    # the colours resolve the barely seen half: everything above the median is "seen" (brightest)
    positive = visibility[visibility > 0]
    low = float(torch.quantile(positive, 0.01)) if len(positive) else 1e-3
    high = max(float(torch.quantile(visibility, 0.5)), low * 10)
    lut = viridis_lut()
    shade = (visibility.clamp(low, high).log() - math.log(low)) / (math.log(high) - math.log(low))
    gaussian_colours = lut[(shade * 255).round().long()].to(avatar.device)
    with torch.no_grad():
        means, quats = avatar.pose(torch.zeros(NUM_JOINTS, 3), torch.zeros(3))
        panels = []
        for _, direction, up in CANONICAL_VIEWS:
            camera = _panel_camera(means.cpu(), direction, up)
            out = rasterization(means, quats, avatar.scales, avatar.opacities, gaussian_colours, camera, background=torch.ones(3))
            panels.append((out.image.clamp(0, 1).cpu() * 255).round().byte().numpy())
    title_height, name_height = 40, 28
    body = np.concatenate(panels, axis=1)
    bar = _colour_bar(lut, low, high, PANEL_SIZE, "mean visibility per frame (pixels)")
    canvas = np.full((title_height + name_height + PANEL_SIZE, body.shape[1] + bar.shape[1], 3), 255, np.uint8)
    canvas[title_height + name_height :, : body.shape[1]] = body
    canvas[title_height + name_height :, body.shape[1] :] = bar
    _text(canvas, title, canvas.shape[1] // 2, 28, 0.7)
    for index, (name, _, _) in enumerate(CANONICAL_VIEWS):
        _text(canvas, name, index * PANEL_SIZE + PANEL_SIZE // 2, title_height + 20)
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
