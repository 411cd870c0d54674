"""A simulated user that paints a suggested image the way a careful person would, from the exact truth.

The person compares the suggested render with the subject's ground truth in the pose the avatar shows
(`SyntheticSubject.render_posed_like`: an avatar on a fitted skeleton stands a little differently from
the subject in the same joint angles, and the person judges the avatar, not its skeleton's fit), with
the same camera, and sees three kinds of wrong region:

- background: the avatar shows something (alpha > 0.5, or visibly non-white) where the truth is
  background (coverage < 0.5): painted white, so apply-edit deletes it;
- colour: both show the subject but the colours differ visibly: painted the true colour;
- missing: the truth shows the subject where the avatar shows (near-)white: painted the true colour.

A pixel is wrong when the mean absolute difference over the channels exceeds `colour_tolerance` after
a small Gaussian blur of the difference (the blur hides single-pixel noise, as an eye at normal zoom
does), and no shift of the truth by up to `outline_tolerance` of the image height explains it. A
person sees the avatar alone: a limb drawn a few pixels beside where the subject's would be, or a stripe
a pixel off, looks right, so the difference at a pixel is the smaller of the differences to the truth's
pixels within that distance, taken both ways (avatar against the truth nearby and truth against the avatar
nearby, the larger of the two), and what a small displacement explains is never painted. Its kind
follows from the unblurred coverage of truth and avatar. The person paints two things:
white (background pixels) and true colours (colour and missing pixels together, so a hole inside a
miscoloured patch is one stroke). Each of the two masks is opened with a 3x3 square (lines thinner
than 3 px are seams nobody paints) and grown back by one pixel inside the mask (so corners and tips
of the broad regions stay), then split into 8-connected blobs; blobs under `min_region_pixels` are
ignored. Blobs are painted most wrong first (`priority="error"`: the largest sum of the blurred
difference over the blob's pixels, so a glaring floater comes before a wide, faintly off patch; the
person fixes what looks worst) or largest first (`priority="area"`: most pixels), while their strokes
fit in the budget; a blob whose stroke would overrun the budget is skipped whole and the next ones are
still tried. Only when no blob fits at all does the person paint part of the first one: its pixels
within the largest distance of its most wrong pixel whose stroke fits (the worst spot, as far as the
budget goes), so a subject with nothing but large wrong regions still gets an edit.

A stroke covers its blob fully and fades out beyond it like a soft brush: weight 1 - d / (feather + 1)
at distance d px from the blob, so with the default 1 px feather the ring of pixels around a blob gets
a partial coat. The ring's paint is the mean paint of the blob pixels within reach. The "exact" style
paints each pixel's true colour, "flat" (the paper's inpaint tool) each blob's mean true colour;
background blobs are white in both. Every pixel outside the strokes keeps the suggested value exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.io.pose_json import PoseFile
from avatarperfect_cli.render.mesh_raster import MeshRender
from avatarperfect_cli.sample.subject import SyntheticSubject

STYLES = ("exact", "flat")
TRUTH_POSES = ("avatar", "suggested")
PRIORITIES = ("area", "error")
KINDS = ("background", "colour", "missing")
_WHITE = np.ones(3, np.float32)


@dataclass
class UserConfig:
    """How the simulated user paints.

    style:              "exact" (true colour per pixel) or "flat" (each blob's mean true colour)
    budget:             most pixels the strokes may touch, as a share of the subject's pixels
                        (truth foreground or avatar showing), feathered edges included
    colour_tolerance:   smallest visible difference: mean absolute error over RGB in [0, 1], after the blur
    min_region_pixels:  blobs smaller than this (after the clean-up) are specks nobody paints
    brush_feather_px:   width of the stroke's soft edge beyond the blob, pixels (0: a hard brush)
    blur_sigma_px:      standard deviation of the Gaussian blur before judging differences, pixels
    priority:           "error" (the blobs with the largest summed difference first) or "area" (most pixels first)
    outline_tolerance:  largest displacement the person overlooks, as a share of the image height (0.006: 3 px
                        at 512², 2 px at 256²; 0: every pixel is compared with the same pixel of the truth)
    truth_pose:         the truth the person pictures (the `simulate-user` stage renders it): "avatar", the subject
                        with its joints where the avatar's skeleton puts them; "suggested", the subject in the
                        suggested joint angles on its own skeleton (a fitted skeleton's outlines then differ)
    """

    style: str = "exact"
    budget: float = 0.15
    colour_tolerance: float = 0.08
    min_region_pixels: int = 16
    brush_feather_px: float = 1.0
    blur_sigma_px: float = 1.0
    priority: str = "error"
    outline_tolerance: float = 0.006
    truth_pose: str = "avatar"

    def __post_init__(self) -> None:
        if self.style not in STYLES:
            raise AvatarPerfectError(f"unknown painting style {self.style!r}; choose one of {', '.join(STYLES)}")
        if self.truth_pose not in TRUTH_POSES:
            raise AvatarPerfectError(f"unknown truth pose {self.truth_pose!r}; choose one of {', '.join(TRUTH_POSES)}")
        if self.priority not in PRIORITIES:
            choices = ", ".join(PRIORITIES)
            raise AvatarPerfectError(f"unknown painting priority {self.priority!r}; choose one of {choices}")
        if not 0.0 < self.budget <= 1.0:
            raise AvatarPerfectError(f"the painting budget is a share of the subject in (0, 1], got {self.budget}")
        if self.colour_tolerance <= 0.0 or self.min_region_pixels < 1:
            raise AvatarPerfectError("the colour tolerance must be positive and min_region_pixels at least 1")
        if self.brush_feather_px < 0.0 or self.blur_sigma_px < 0.0 or not 0.0 <= self.outline_tolerance < 0.5:
            raise AvatarPerfectError("the brush feather and the blur must not be negative, the outline tolerance in [0, 0.5)")


@dataclass
class PaintStats:
    """What the user saw and painted, in pixels.

    subject_pixels:  truth foreground or avatar showing
    budget_pixels:   floor(budget * subject_pixels)
    painted_pixels:  pixels the strokes touch, feathered edges included (<= budget_pixels)
    budget_used:     painted_pixels / budget_pixels (0 when the budget is 0 pixels)
    wrong_pixels:    per kind (KINDS), pixels of all the blobs found
    painted_by_kind: per kind, pixels of the blobs painted (their feathered edges not counted)
    blobs_found, blobs_painted: blob counts
    """

    subject_pixels: int
    budget_pixels: int
    painted_pixels: int
    budget_used: float
    wrong_pixels: dict[str, int]
    painted_by_kind: dict[str, int]
    blobs_found: int
    blobs_painted: int


@dataclass
class PaintResult:
    """image: (H, W, 3) float32 in [0, 1], the edited image; stroke_weight: (H, W) float32 in [0, 1], how much
    paint covers each pixel (0 where the image is the suggested one); stats: the counts."""

    image: torch.Tensor
    stroke_weight: torch.Tensor
    stats: PaintStats


@dataclass
class _Blob:
    white: bool  # painted white (background), else in true colours
    label: int  # its label in its paint's component image
    area: int
    error: float  # sum over its pixels of the blurred difference
    box: tuple[int, int, int, int]  # x, y, width, height


def pictured_truth(
    subject: SyntheticSubject, pose: PoseFile, rest_joints: torch.Tensor, transl_offset: torch.Tensor, truth_pose: str
) -> MeshRender:
    """The truth the person compares a suggestion in `pose` (the avatar's pose file) with (`UserConfig.truth_pose`):
    the subject where the avatar on `rest_joints` (24, 3) stands, or in the suggested joint angles at the pose's
    translation less `transl_offset` (3,) metres, the workspace's offset."""
    if truth_pose == "avatar":
        return subject.render_posed_like(pose.body_pose, pose.transl, rest_joints, pose.camera)
    return subject.render(pose.body_pose, pose.transl - transl_offset, pose.camera)


def paint(
    suggested: torch.Tensor, suggested_alpha: torch.Tensor, truth: MeshRender, config: UserConfig | None = None
) -> PaintResult:
    """Paint the suggested image where it is wrong, as described in the module docstring. Deterministic.

    suggested:       (H, W, 3) float in [0, 1], the render on white as read from its PNG
    suggested_alpha: (H, W) the avatar's accumulated opacity in [0, 1]
    truth:           the ground truth at the same pose and camera, on white (SyntheticSubject.render)
    """
    config = config or UserConfig()
    image = suggested.detach().cpu().float().numpy()
    alpha = suggested_alpha.detach().cpu().float().numpy()
    height, width = image.shape[:2]
    if image.shape != (height, width, 3) or alpha.shape != (height, width) or truth.rgb.shape != image.shape:
        raise ValueError(
            f"suggested {image.shape}, alpha {alpha.shape} and truth {truth.rgb.shape} "
            "must be (H, W, 3), (H, W) and (H, W, 3)"
        )
    truth_rgb = truth.rgb.astype(np.float32)
    truth_shows = truth.coverage >= 0.5
    avatar_shows = (alpha > 0.5) | (np.abs(image - _WHITE).mean(axis=2) > config.colour_tolerance)
    shift = round(config.outline_tolerance * height)
    difference = _blurred_difference(image, truth_rgb, config.blur_sigma_px, shift)
    wrong = difference > config.colour_tolerance
    kind = np.full((height, width), -1, np.int8)  # index into KINDS of each wrong pixel
    kind[wrong & avatar_shows & ~truth_shows] = KINDS.index("background")
    kind[wrong & avatar_shows & truth_shows] = KINDS.index("colour")
    kind[wrong & ~avatar_shows & truth_shows] = KINDS.index("missing")

    component_images = {}  # white (bool) -> (H, W) int32 blob labels
    blobs = []
    for white, mask in ((True, kind == KINDS.index("background")), (False, wrong & truth_shows)):
        count, labels, stats, _ = cv2.connectedComponentsWithStats(_clean_up(mask), connectivity=8)
        component_images[white] = labels
        errors = np.bincount(labels.ravel(), difference.ravel(), minlength=count)
        for label in range(1, count):
            x, y, w, h, area = (int(v) for v in stats[label])
            if area >= config.min_region_pixels:
                blobs.append(_Blob(white, label, area, float(errors[label]), (x, y, w, h)))
    size = (lambda blob: blob.area) if config.priority == "area" else (lambda blob: blob.error)
    blobs.sort(key=lambda blob: (-size(blob), not blob.white, blob.label))

    subject_pixels = int((truth_shows | avatar_shows).sum())
    budget_pixels = math.floor(config.budget * subject_pixels)
    reach = config.brush_feather_px + 1.0  # stroke weight 1 - d / reach at distance d from the blob
    found = _pixels_of(blobs, component_images, white=True) | _pixels_of(blobs, component_images, white=False)
    chosen = _choose_blobs(blobs, component_images, reach, budget_pixels, (height, width))
    if not chosen and blobs:
        first = blobs[0]
        chosen = _clip_blob(first, component_images[first.white], difference, reach, budget_pixels)

    in_white = _pixels_of(chosen, component_images, white=True)
    in_colour = _pixels_of(chosen, component_images, white=False)
    interior = in_white | in_colour
    colours = np.zeros((height, width, 3), np.float32)
    colours[in_white] = _WHITE
    if config.style == "exact":
        colours[in_colour] = truth_rgb[in_colour]
    else:
        colours[in_colour] = _blob_means(truth_rgb, component_images[False])[component_images[False][in_colour]]
    weight, footprint = _stroke_weight(interior, reach)
    paint_layer = _spread_into_ring(colours, interior, math.ceil(reach))
    blend = image * (1.0 - weight[..., None]) + paint_layer * weight[..., None]
    edited = np.where(footprint[..., None], blend, image)

    painted_pixels = int(footprint.sum())
    stats = PaintStats(
        subject_pixels=subject_pixels,
        budget_pixels=budget_pixels,
        painted_pixels=painted_pixels,
        budget_used=painted_pixels / budget_pixels if budget_pixels else 0.0,
        wrong_pixels=_count_kinds(kind, found),
        painted_by_kind=_count_kinds(kind, interior),
        blobs_found=len(blobs),
        blobs_painted=len(chosen),
    )
    return PaintResult(torch.from_numpy(edited.astype(np.float32)), torch.from_numpy(weight), stats)


def _clean_up(mask: np.ndarray) -> np.ndarray:
    """(H, W) uint8 0/1: `mask` (H, W) bool opened by a 3x3 square, then grown back by one pixel inside
    `mask`, so the thin parts are dropped while the corners and tips of the broad parts stay."""
    square = np.ones((3, 3), np.uint8)
    mask = mask.astype(np.uint8)
    opened = cv2.morphologyEx(mask, cv2.MORPH_OPEN, square)
    return cv2.dilate(opened, square) & mask


def _pixels_of(blobs: list[_Blob], component_images: dict[bool, np.ndarray], white: bool) -> np.ndarray:
    """(H, W) bool: the pixels of those `blobs` painted white (white=True) or in true colours (False)."""
    labels = component_images[white]
    selected = np.zeros(int(labels.max()) + 1, bool)
    selected[[blob.label for blob in blobs if blob.white == white]] = True
    selected[0] = False
    return selected[labels]


def _blob_means(rgb: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(L, 3) float32 mean colour of rgb (H, W, 3) over each label of `labels` (H, W) int32 in [0, L)."""
    count = np.bincount(labels.ravel()).astype(np.float64)
    sums = np.stack([np.bincount(labels.ravel(), rgb[..., c].ravel(), minlength=len(count)) for c in range(3)], axis=1)
    return (sums / np.maximum(count, 1.0)[:, None]).astype(np.float32)


def _count_kinds(kind: np.ndarray, where: np.ndarray) -> dict[str, int]:
    """Pixels of each of KINDS among `where` (H, W) bool, from the kind map (H, W) (-1: not wrong)."""
    counts = np.bincount(kind[where & (kind >= 0)], minlength=len(KINDS))
    return {name: int(count) for name, count in zip(KINDS, counts)}


def _blurred_difference(image: np.ndarray, reference: np.ndarray, sigma: float, shift: int) -> np.ndarray:
    """(H, W) mean over channels of |blur(image) - blur(reference)|, image and reference (H, W, 3); with
    `shift` > 0 px, the smallest such difference to the other image's pixels within `shift` px (a disc),
    taken both ways and the larger of the two kept: what a displacement of up to `shift` px explains."""
    blurred = []
    for rgb in (image, reference):
        rgb = np.ascontiguousarray(rgb, dtype=np.float32)
        if sigma > 0.0:
            rgb = cv2.GaussianBlur(rgb, (0, 0), sigmaX=sigma, borderType=cv2.BORDER_REPLICATE)
        blurred.append(rgb)
    return np.maximum(_nearest_difference(*blurred, shift), _nearest_difference(*blurred[::-1], shift))


def _nearest_difference(image: np.ndarray, reference: np.ndarray, shift: int) -> np.ndarray:
    """(H, W) for each pixel of `image` (H, W, 3), the smallest mean absolute channel difference to the
    pixels of `reference` (H, W, 3) within `shift` px of it (the image's edges repeated beyond it)."""
    height, width = image.shape[:2]
    padded = cv2.copyMakeBorder(reference, shift, shift, shift, shift, cv2.BORDER_REPLICATE)
    nearest = np.full((height, width), np.inf, np.float32)
    for dy in range(-shift, shift + 1):
        for dx in range(-shift, shift + 1):
            if dy * dy + dx * dx <= shift * shift:
                moved = padded[shift + dy : shift + dy + height, shift + dx : shift + dx + width]
                np.minimum(nearest, cv2.absdiff(image, moved).mean(axis=2), out=nearest)
    return nearest


def _distance_to(mask: np.ndarray) -> np.ndarray:
    """(H, W) float32 exact Euclidean distance in pixels from each pixel to the nearest True pixel of `mask`."""
    return cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def _stroke_window(blob: _Blob, reach: float, size: tuple[int, ...]) -> tuple[slice, slice]:
    """(rows, cols): the blob's box grown by the stroke's reach, within an image of `size` (H, W)."""
    x, y, w, h = blob.box
    pad = math.ceil(reach)
    return slice(max(y - pad, 0), min(y + h + pad, size[0])), slice(max(x - pad, 0), min(x + w + pad, size[1]))


def _choose_blobs(
    blobs: list[_Blob],
    component_images: dict[bool, np.ndarray],
    reach: float,
    budget_pixels: int,
    size: tuple[int, int],
) -> list[_Blob]:
    """The blobs (already ordered by priority) whose strokes (pixels closer than `reach` to the blob) fit
    together in `budget_pixels`; a blob that does not fit is skipped."""
    covered = np.zeros(size, bool)
    used = 0
    chosen = []
    for blob in blobs:
        rows, cols = _stroke_window(blob, reach, size)
        stroke = _distance_to(component_images[blob.white][rows, cols] == blob.label) < reach
        added = int((stroke & ~covered[rows, cols]).sum())
        if used + added > budget_pixels:
            continue
        covered[rows, cols] |= stroke
        used += added
        chosen.append(blob)
    return chosen


def _clip_blob(blob: _Blob, labels: np.ndarray, difference: np.ndarray, reach: float, budget_pixels: int) -> list[_Blob]:
    """[blob cut down to its pixels within the largest distance of its most wrong pixel (largest
    `difference` (H, W)) whose stroke fits `budget_pixels`], or [] when not even that pixel's does. The cut
    edits `labels` (H, W) in place: the rest of the blob is unlabelled."""
    rows, cols = _stroke_window(blob, reach, labels.shape)
    inside = labels[rows, cols] == blob.label
    peak = np.unravel_index(np.argmax(np.where(inside, difference[rows, cols], -np.inf)), inside.shape)
    row_index, col_index = np.indices(inside.shape)
    from_peak = np.hypot(row_index - peak[0], col_index - peak[1])
    radii = np.unique(from_peak[inside])

    def stroke_pixels(radius: float) -> int:
        return int((_distance_to(inside & (from_peak <= radius)) < reach).sum())

    fits, too_big = -1, len(radii)  # strokes grow with the radius: the largest index that fits
    while too_big - fits > 1:
        middle = (fits + too_big) // 2
        fits, too_big = (middle, too_big) if stroke_pixels(radii[middle]) <= budget_pixels else (fits, middle)
    if fits < 0:
        return []
    labels[rows, cols][inside & (from_peak > radii[fits])] = 0
    return [_Blob(blob.white, blob.label, int((inside & (from_peak <= radii[fits])).sum()), blob.error, blob.box)]


def _stroke_weight(interior: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Soft-brush coverage of the painted blobs `interior` (H, W) bool: weight (H, W) float32, 1 inside and
    1 - d / reach at distance d px outside, and the footprint (H, W) bool where d < reach."""
    distance = _distance_to(interior)
    footprint = distance < reach
    weight = np.where(footprint, np.clip(1.0 - distance / np.float32(reach), 0.0, 1.0), 0.0).astype(np.float32)
    return weight, footprint


def _spread_into_ring(colours: np.ndarray, interior: np.ndarray, radius: int) -> np.ndarray:
    """(H, W, 3) paint: `colours` inside `interior`, elsewhere the mean of the interior colours in the
    (2 radius + 1)^2 window around the pixel (white where there are none)."""
    size = (2 * radius + 1, 2 * radius + 1)
    inside = interior.astype(np.float32)
    total = cv2.boxFilter(colours * inside[..., None], -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    count = cv2.boxFilter(inside, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    ring = np.where(count[..., None] > 0.5, total / np.maximum(count, 1.0)[..., None], _WHITE)
    return np.where(interior[..., None], colours, ring).astype(np.float32)
