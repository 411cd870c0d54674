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


def visibility_picture(avatar: Avatar, visibility: torch.Tensor, title: str) -> bytes:
    """PNG bytes: the canonical avatar (T-pose) from the front, both sides, the back and below, each
    Gaussian coloured by its accumulated visibility V (N,) on a logarithmic perceptual colour map
    (dark: barely seen), with a colour bar. Rendered on the avatar's device; `visibility` on the CPU."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import colormaps, colors
    from matplotlib import pyplot as plt

    # the colours resolve the barely seen half: everything above the median is "seen" (brightest)
    positive = visibility[visibility > 0]
    low = float(torch.quantile(positive, 0.01)) if len(positive) else 1e-3
    high = max(float(torch.quantile(visibility, 0.5)), low * 10)
    norm = colors.LogNorm(vmin=low, vmax=high)
    colour_map = colormaps["viridis"]
    gaussian_colours = torch.from_numpy(colour_map(norm(visibility.clamp(low, high).numpy()))[:, :3]).float()
    gaussian_colours = gaussian_colours.to(avatar.device)
    with torch.no_grad():
        means, quats = avatar.pose(torch.zeros(NUM_JOINTS, 3), torch.zeros(3))
        panels = []
        for _, direction, up in CANONICAL_VIEWS:
            camera = _panel_camera(means.cpu(), direction, up)
            out = rasterization(means, quats, avatar.scales, avatar.opacities, gaussian_colours, camera, background=torch.ones(3))
            panels.append(out.image.clamp(0, 1).cpu().numpy())
    figure, axes = plt.subplots(1, len(panels) + 1, figsize=(3.2 * len(panels) + 0.8, 3.9),
                                gridspec_kw={"width_ratios": [1] * len(panels) + [0.06]})  # fmt: skip
    for axis, panel, (name, _, _) in zip(axes, panels, CANONICAL_VIEWS):
        axis.imshow(panel)
        axis.set_title(name)
        axis.axis("off")
    bar = figure.colorbar(matplotlib.cm.ScalarMappable(norm=norm, cmap=colour_map), cax=axes[-1])
    bar.set_label("mean visibility per frame (pixels)")
    return figure_png(figure, title)


def figure_png(figure, title: str) -> bytes:
    """PNG bytes of a matplotlib figure with `title`, laid out tightly; the figure is closed."""
    from matplotlib import pyplot as plt

    figure.suptitle(title)
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=100)
    plt.close(figure)
    return buffer.getvalue()


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
