"""The static background behind a fixed camera's subject, estimated from the video itself.

A turn-around or a walk in front of a fixed camera shows most background pixels in some frames: each
pixel's backdrop colour is its mean over the frames where the subject's mask, grown by `margin` pixels
(masks err by a few pixels at their edge), stays away from it. It is known where enough frames saw it and
they agree (a static background, a steady camera). A pixel the subject always hides, within `reach` of
seen ones, takes their colours (inpainting: a wall or a floor goes on behind the subject). Elsewhere it is
NaN: deep behind the subject, or a background that moves, flickers or was filmed handheld.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch


@dataclass
class BackdropConfig:
    """margin: pixels the masks grow by before a pixel counts as background; min_frames: frames that must
    have seen a pixel (and at least `min_share` of the video); max_spread: largest standard deviation of
    its colour over those frames, in [0, 1] (compression noise is about 0.01); reach: pixels from the
    nearest seen one that an unseen pixel is filled up to (0: none)."""

    margin: int = 5
    min_frames: int = 3
    min_share: float = 0.1
    max_spread: float = 0.05
    reach: int = 12


def estimate_backdrop(frames: torch.Tensor, masks: torch.Tensor, config: BackdropConfig | None = None) -> torch.Tensor:
    """(H, W, 3) float32 backdrop colours in [0, 1], NaN where unknown.

    frames: (T, H, W, 3) uint8 RGB as filmed; masks: (T, H, W) bool, True on the subject."""
    config = config or BackdropConfig()
    kernel = np.ones((2 * config.margin + 1,) * 2, np.uint8)
    height, width = masks.shape[1:]
    count = np.zeros((height, width), np.float64)
    total = np.zeros((height, width, 3), np.float64)
    total_sq = np.zeros((height, width, 3), np.float64)
    for frame, mask in zip(frames.numpy(), masks.numpy()):
        seen = cv2.dilate(mask.astype(np.uint8), kernel) == 0
        colours = frame.astype(np.float64) / 255.0 * seen[..., None]
        count += seen
        total += colours
        total_sq += colours * colours
    needed = max(config.min_frames, config.min_share * len(frames))
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = total / count[..., None]
        spread = np.sqrt(np.maximum(total_sq / count[..., None] - mean * mean, 0.0)).max(axis=-1)
    known = (count >= needed) & (spread <= config.max_spread)
    backdrop = np.where(known[..., None], mean, 0.0).astype(np.float32)
    if config.reach and known.any() and not known.all():
        unseen = (~known).astype(np.uint8)
        filled = cv2.inpaint(np.round(backdrop * 255).astype(np.uint8), unseen, 3, cv2.INPAINT_TELEA)
        distance = cv2.distanceTransform(unseen, cv2.DIST_L2, 3)
        reached = (distance <= config.reach) & ~known
        backdrop[reached] = filled[reached].astype(np.float32) / 255
        known |= reached
    return torch.from_numpy(np.where(known[..., None], backdrop, np.nan).astype(np.float32))
