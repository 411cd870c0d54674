"""Where a body template lands under poses fitted for another body, and the translation that fixes it.

SMPL places a posed body at its rest pelvis J0(betas) + transl. A template whose rest pelvis sits elsewhere
(anny's is about 0.43 m from SMPL's along the body's up axis) lands offset by the difference when it is
driven by SMPL-fitted translations. The root joint lands at rest pelvis + transl whatever the pose, so one
world-frame offset added to every frame's transl moves the template onto the subject.

The offset is estimated from the data, not guessed: the template's silhouette (its initial Gaussians'
alpha) is rendered at a few frames and slid over the subject masks; the image shift with the best mean IoU
over those frames, taken back to metres at the body's depth, updates the offset, and the renders are
repeated at the new offset (the shift of a 3-D translation is not exactly uniform across the body).
The search covers shifts up to the image size in every direction, so no starting guess is needed.
It fits the offset in the image plane (the camera's right and down axes): along the viewing direction a
silhouette only tells the body's size, and the template's size differs from the subject's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.body import BodyTemplate, forward_kinematics
from avatarperfect_cli.datasets import VideoDataset
from avatarperfect_cli.datasets.people_snapshot import downscaled_camera
from avatarperfect_cli.render import Camera


# The template's initial Gaussians are discs as wide as their vertex's share of the surface; their alpha
# spreads past the mesh's outline. Shrunk by this factor it stays inside the outline, with gaps between the
# discs along the limbs that lower the soft IoU about alike at every shift, so the search's peak stands
# (the fit's picture and IoU draw the mesh itself: `body_fit.body_silhouette`).
SILHOUETTE_SHRINK = 0.5


@dataclass
class OffsetSearch:
    """frames: video frames compared (evenly spaced); resolution: longest image side of the comparison in
    pixels (at most the video's); rounds: render-and-align repetitions."""

    frames: int = 8
    resolution: int = 128
    rounds: int = 3


@dataclass
class OffsetFit:
    """offset: (3,) metres, world frame, to add to every frame's transl; iou: mean soft IoU of the
    template's alpha and the masks over the compared frames at the last alignment."""

    offset: torch.Tensor
    iou: float


def fit_transl_offset(template: BodyTemplate, video: VideoDataset, search: OffsetSearch | None = None) -> OffsetFit:
    """The translation offset that puts `template`, posed by the video's poses, on the video's masks."""
    search = search or OffsetSearch()
    camera, masks = _comparison_frames(video, search.resolution)
    chosen = torch.linspace(0, len(video) - 1, min(search.frames, len(video))).round().long().unique()
    masks = masks[chosen].numpy()
    body_pose, transl = video.body_pose[chosen].float(), video.transl[chosen].float()
    silhouette = silhouette_avatar(template)
    canvas = _canvas(camera)
    rotation = camera.world_to_camera[:3, :3]
    offset = torch.zeros(3)
    iou = 0.0
    for _ in range(search.rounds):
        scores = np.zeros((2 * camera.height + 1, 2 * camera.width + 1), np.float64)
        with torch.no_grad():
            for body, root_transl, mask in zip(body_pose, transl, masks):
                alpha = render_avatar(silhouette, body, root_transl + offset, canvas, torch.zeros(3)).alpha
                scores += _shift_iou(alpha.numpy().astype(np.float32), mask)
        scores /= len(masks)
        row, col = _subpixel_peak(scores)
        iou = float(scores.max())
        shift_x, shift_y = camera.width - col, camera.height - row  # pixels to move the template by
        depth = _mean_root_depth(silhouette.rest_joints, body_pose, transl + offset, camera)
        offset = offset + depth * (shift_x / float(camera.K[0, 0]) * rotation[0] + shift_y / float(camera.K[1, 1]) * rotation[1])
    return OffsetFit(offset, iou)


def silhouette_avatar(template: BodyTemplate) -> Avatar:
    """The template's initial Gaussians, shrunk so that their alpha hugs the mesh's outline."""
    silhouette = Avatar.from_template(template, sh_degree=0)
    silhouette.params["log_scales"] = silhouette.params["log_scales"] + math.log(SILHOUETTE_SHRINK)
    return silhouette


def _comparison_frames(video: VideoDataset, resolution: int) -> tuple[Camera, torch.Tensor]:
    """The video's camera and masks (T, h, w) float32 in [0, 1] (area-averaged) at about `resolution` pixels."""
    factor = max(1, round(max(video.camera.width, video.camera.height) / resolution))
    camera = downscaled_camera(video.camera, factor)
    masks = F.interpolate(video.masks.float()[:, None], size=(camera.height, camera.width), mode="area")[:, 0]
    return camera, masks


def _canvas(camera: Camera) -> Camera:
    """The camera with its image grown by its own size on every side (the image is the middle third),
    so that the template stays in view wherever the offset puts it."""
    K = camera.K.clone()
    K[0, 2] += camera.width
    K[1, 2] += camera.height
    return Camera(K, camera.world_to_camera, 3 * camera.width, 3 * camera.height)


def _shift_iou(alpha: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(2h+1, 2w+1) soft IoU of `mask` (h, w) and the canvas alpha (3h, 3w) seen through an image window
    placed at each offset; the window at (h, w) is the image, so entry (h - dy, w - dx) is the IoU after
    moving the template by (dx, dy) pixels."""
    intersection = cv2.matchTemplate(alpha, mask, cv2.TM_CCORR)
    alpha_in_window = cv2.matchTemplate(alpha, np.ones_like(mask), cv2.TM_CCORR)
    union = alpha_in_window + float(mask.sum()) - intersection
    return intersection / np.maximum(union, 1e-6)


def _subpixel_peak(scores: np.ndarray) -> tuple[float, float]:
    """(row, col) of the maximum of `scores`, refined by a parabola through it and its neighbours per axis."""
    row, col = np.unravel_index(int(np.argmax(scores)), scores.shape)
    refined = []
    for axis, index in ((0, row), (1, col)):
        line = scores[:, col] if axis == 0 else scores[row, :]
        if 0 < index < len(line) - 1:
            below, peak, above = line[index - 1], line[index], line[index + 1]
            curvature = below - 2.0 * peak + above
            refined.append(index + (0.5 * (below - above) / curvature if curvature < 0 else 0.0))
        else:
            refined.append(float(index))
    return refined[0], refined[1]


def _mean_root_depth(rest_joints: torch.Tensor, body_pose: torch.Tensor, transl: torch.Tensor, camera: Camera) -> float:
    """Mean camera-frame z (metres) of the posed root joint over frames (body_pose (T, 24, 3), transl (T, 3))."""
    roots = forward_kinematics(body_pose, rest_joints, transl)[:, 0] @ torch.cat([rest_joints[0], torch.ones(1)])
    in_camera = roots[:, :3] @ camera.world_to_camera[:3, :3].T + camera.world_to_camera[:3, 3]
    return float(in_camera[:, 2].mean())
