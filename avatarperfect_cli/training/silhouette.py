"""Silhouette distances between a posed body template and person masks, in pixels, differentiable in the
posed points: what the body fit and the pose fit minimise.

    outside   each projected template point's distance outside its frame's mask (the mask's distance
              transform, sampled bilinearly): no part of the body sticks out of the person;
    coverage  each mask-contour pixel's distance to the nearest projected template point (an exact grid
              search): the body fills the person's outline.
Both are Huber-robust, so a mask a few pixels off at its border moves nothing far.

A person the frame cuts off (feet below its lower edge, a head above it) goes on past that edge, unseen:
points projected past an image edge that the mask touches count as inside, and where the mask is cut along
an image edge, that cut is not part of its contour. Without that, a video cropped at the shins fitted the custom
subject's rest joints 13 cm from the truth instead of 0.5 cm.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numba
import numpy as np
import torch
import torch.nn.functional as F

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.body import BodyTemplate, forward_kinematics, skin_points
from avatarperfect_cli.datasets import VideoDataset
from avatarperfect_cli.datasets.people_snapshot import downscaled_camera
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.render import Camera


@dataclass
class Silhouettes:
    """The compared frames at the fit's resolution: camera, poses (T, 24, 3), transl (T, 3), outside distance
    transforms (T, 1, h, w) in pixels, contour pixel centres (T, M, 2), and cut (T, 4) bool: whether the
    mask touches the image's top, bottom, left and right edge (the person goes on past it)."""

    camera: Camera
    body_pose: torch.Tensor
    transl: torch.Tensor
    outside: torch.Tensor
    contours: torch.Tensor
    cut: torch.Tensor


@dataclass
class SkinnedPoints:
    """Points that stand for a body's surface: points (P, 3) canonical, metres; weights (P, 24) skinning
    weights; rest_joints (24, 3) metres."""

    points: torch.Tensor
    weights: torch.Tensor
    rest_joints: torch.Tensor

    @classmethod
    def of_template(cls, template: BodyTemplate, count: int) -> SkinnedPoints:
        """`count` template vertices drawn by surface area (`surface_points`)."""
        chosen = surface_points(template.vertices.float(), template.faces, count)
        return cls(template.vertices[chosen].float(), template.weights[chosen].float(), template.rest_joints.float())

    @classmethod
    def of_avatar(cls, avatar: Avatar, count: int) -> SkinnedPoints:
        """The centres of `count` of the avatar's opaque Gaussians (opacity above 0.5; a fixed draw)."""
        opaque = torch.nonzero(avatar.opacities.detach().cpu() > 0.5).flatten()
        generator = torch.Generator().manual_seed(0)
        chosen = opaque[torch.randperm(len(opaque), generator=generator)[:count]]
        return cls(
            avatar.params["means"].detach().cpu()[chosen].float(),
            avatar.skin_weights.detach().cpu()[chosen].float(),
            avatar.rest_joints.cpu().float(),
        )

    def posed(self, body_pose: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
        """(T, P, 3) world-frame points for poses (T, 24, 3) and translations (T, 3)."""
        return skin_points(self.points, self.weights, forward_kinematics(body_pose, self.rest_joints, transl))


def check_masks(video: VideoDataset) -> None:
    """Raise AvatarPerfectError naming the first frame whose mask is empty or fills the whole frame."""
    covered = video.masks.flatten(1).float().mean(dim=1)
    unfit = torch.nonzero((covered == 0) | (covered == 1)).flatten()
    if len(unfit):
        index = int(unfit[0])
        what = "empty" if covered[index] == 0 else "the whole frame"
        raise AvatarPerfectError(f"the mask of frame {int(video.frame_ids[index])} is {what}: no body to fit")


# The image edges in the column order of `touched_edges`.
EDGES = ("top", "bottom", "left", "right")


def touched_edges(masks: np.ndarray) -> np.ndarray:
    """(T, 4) bool: whether each mask (T, H, W) reaches the image's top, bottom, left and right edge (`EDGES`),
    where the frame cuts the person off and the person goes on past it."""
    rows, columns = masks.any(axis=2), masks.any(axis=1)  # (T, H) and (T, W): what the person covers
    return np.stack([rows[:, 0], rows[:, -1], columns[:, 0], columns[:, -1]], axis=1)


def silhouettes(video: VideoDataset, frames: torch.Tensor, resolution: int, contour_pixels: int) -> Silhouettes:
    """The masks of `frames` (indices into the video) at about `resolution` pixels as distance fields.

    Raises AvatarPerfectError naming the frame when a mask is empty or fills the whole frame.
    """
    factor = max(1, round(max(video.camera.width, video.camera.height) / resolution))
    camera = downscaled_camera(video.camera, factor)
    check_masks(video)
    generator = np.random.default_rng(0)
    outside, contours, cut = [], [], []
    for index in frames.tolist():
        fine = video.masks[index]
        mask = F.interpolate(fine.float()[None, None], size=(camera.height, camera.width), mode="area")[0, 0] >= 0.5
        mask = mask.numpy().astype(np.uint8)
        outside.append(cv2.distanceTransform(1 - mask, cv2.DIST_L2, 5))
        cut.append(touched_edges(mask[None])[0])
        border = mask & ~cv2.erode(mask, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE).astype(bool)
        rows, cols = np.nonzero(border if border.any() else mask)
        chosen = generator.choice(len(rows), contour_pixels, replace=len(rows) < contour_pixels)
        contours.append(np.stack([cols[chosen], rows[chosen]], axis=1) + 0.5)
    return Silhouettes(
        camera,
        video.body_pose[frames].float(),
        video.transl[frames].float(),
        torch.from_numpy(np.stack(outside))[:, None],
        torch.from_numpy(np.stack(contours)).float(),
        torch.from_numpy(np.stack(cut)),
    )


def project(points: torch.Tensor, camera: Camera) -> torch.Tensor:
    """(..., 3) world points, metres -> (..., 2) pixel coordinates (x right, y down; pixel centres at +0.5),
    differentiable: the projection the silhouette kernels make (`_project_kernel`), depth clamped alike."""
    rotation, translation, K = camera.world_to_camera[:3, :3], camera.world_to_camera[:3, 3], camera.K
    x, y, z = points.unbind(-1)
    in_camera = [x * row[0] + y * row[1] + z * row[2] + shift for row, shift in zip(rotation, translation)]
    u, v, depth = (in_camera[0] * row[0] + in_camera[1] * row[1] + in_camera[2] * row[2] for row in K)
    depth = depth.clamp_min(1e-3)
    return torch.stack([u / depth, v / depth], dim=-1)


def silhouette_loss(posed: torch.Tensor, data: Silhouettes, huber: float) -> torch.Tensor:
    """(T,) each compared frame's mean outside distance of its posed points plus mean coverage distance of
    its contour pixels, pixels, Huber-robust beyond `huber` pixels. posed: (T, P, 3) template points posed by
    the frames' poses, world frame, metres.

    Computed with its gradient in one pass of numba kernels (`_silhouette_kernel`); the gradient is kept for
    the backward, which only scales it by each frame's incoming gradient."""
    return _SilhouetteLoss.apply(posed, data, huber)


class _SilhouetteLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, posed: torch.Tensor, data: Silhouettes, huber: float) -> torch.Tensor:
        camera = data.camera
        rotation, translation = (t.detach().cpu().double().numpy() for t in (camera.world_to_camera[:3, :3], camera.world_to_camera[:3, 3]))
        K = camera.K.detach().cpu().double().numpy()
        points = posed.detach().cpu().double().numpy()
        pixels, depths = _project_kernel(points, rotation, translation, K)
        contours = data.contours.cpu().double().numpy()
        nearest = _nearest_kernel(pixels, contours, camera.width, camera.height, _NEAREST_CELL)
        loss, gradient = _silhouette_kernel(
            pixels, depths, rotation, K, data.outside[:, 0].cpu().numpy(), contours, data.cut.cpu().numpy(), nearest,
            float(huber), float(camera.width), float(camera.height),
        )  # fmt: skip
        ctx.save_for_backward(torch.from_numpy(gradient).to(posed.device, posed.dtype))
        return torch.from_numpy(loss).to(posed.device, posed.dtype)

    @staticmethod
    def backward(ctx: Any, grad_loss: torch.Tensor) -> tuple[torch.Tensor, None, None]:
        (gradient,) = ctx.saved_tensors
        return grad_loss[:, None, None] * gradient, None, None


# The nearest depth a projected point may have, metres (as `project` clamps it).
_MIN_DEPTH = 1e-3


@numba.njit(cache=True, parallel=True)
def _project_kernel(
    points: np.ndarray, rotation: np.ndarray, translation: np.ndarray, K: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(T, P, 2) pixels of world points (T, P, 3), as `project`, and (T, P) their depths before the clamp."""
    frames, count = points.shape[0], points.shape[1]
    pixels, depths = np.empty((frames, count, 2)), np.empty((frames, count))
    for frame in numba.prange(frames):
        for index in range(count):
            x, y, z = points[frame, index, 0], points[frame, index, 1], points[frame, index, 2]
            c0 = rotation[0, 0] * x + rotation[0, 1] * y + rotation[0, 2] * z + translation[0]
            c1 = rotation[1, 0] * x + rotation[1, 1] * y + rotation[1, 2] * z + translation[1]
            c2 = rotation[2, 0] * x + rotation[2, 1] * y + rotation[2, 2] * z + translation[2]
            depths[frame, index] = K[2, 0] * c0 + K[2, 1] * c1 + K[2, 2] * c2
            depth = max(depths[frame, index], _MIN_DEPTH)
            pixels[frame, index, 0] = (K[0, 0] * c0 + K[0, 1] * c1 + K[0, 2] * c2) / depth
            pixels[frame, index, 1] = (K[1, 0] * c0 + K[1, 1] * c1 + K[1, 2] * c2) / depth
    return pixels, depths


@numba.njit(cache=True, inline="always")
def _huber(distance: float, delta: float) -> tuple[float, float]:
    """The Huber loss of a distance and its derivative."""
    if distance < delta:
        return 0.5 * distance * distance / delta, distance / delta
    return distance - 0.5 * delta, 1.0


@numba.njit(cache=True, inline="always")
def _field(outside: np.ndarray, frame: int, row: int, column: int) -> float:
    """A distance-field value, zero beyond the field (as grid_sample's corners outside it)."""
    if 0 <= row < outside.shape[1] and 0 <= column < outside.shape[2]:
        return outside[frame, row, column]
    return 0.0


@numba.njit(cache=True, parallel=True)
def _silhouette_kernel(
    pixels: np.ndarray, depths: np.ndarray, rotation: np.ndarray, K: np.ndarray, outside: np.ndarray, contours: np.ndarray,
    cut: np.ndarray, nearest: np.ndarray, huber: float, width: float, height: float,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Each frame's loss (T,) as `silhouette_loss` and its gradient (T, P, 3) in the world points.

    pixels (T, P, 2) and depths (T, P) of the world points (`_project_kernel`); outside (T, h, w) distance fields sampled as
    grid_sample does (bilinear, border padding, align_corners=False: pixel x sits at column x - 0.5);
    contours (T, M, 2) pixels and nearest (T, M) the index of each one's nearest projected point."""
    frames, count, contour_count = pixels.shape[0], pixels.shape[1], contours.shape[1]
    loss = np.zeros(frames)
    gradient = np.empty((frames, count, 3))
    for frame in numba.prange(frames):
        pixel_gradient = np.zeros((count, 2))
        total = 0.0
        for index in range(count):
            u, v = pixels[frame, index, 0], pixels[frame, index, 1]
            if (v < 0.0 and cut[frame, 0]) or (v > height and cut[frame, 1]) or (u < 0.0 and cut[frame, 2]) or (u > width and cut[frame, 3]):
                continue  # past an edge the mask touches: unseen, costs nothing
            # the field sampled bilinearly at the clipped coordinate; no gradient where clipped
            column, row = u - 0.5, v - 0.5
            column_slope = 1.0 if 0.0 <= column <= width - 1.0 else 0.0
            row_slope = 1.0 if 0.0 <= row <= height - 1.0 else 0.0
            column, row = min(max(column, 0.0), width - 1.0), min(max(row, 0.0), height - 1.0)
            left, top = int(np.floor(column)), int(np.floor(row))
            fx, fy = column - left, row - top
            nw, ne = _field(outside, frame, top, left), _field(outside, frame, top, left + 1)
            sw, se = _field(outside, frame, top + 1, left), _field(outside, frame, top + 1, left + 1)
            sampled = nw * (1 - fx) * (1 - fy) + ne * fx * (1 - fy) + sw * (1 - fx) * fy + se * fx * fy
            d_column = ((ne - nw) * (1 - fy) + (se - sw) * fy) * column_slope
            d_row = ((sw - nw) * (1 - fx) + (se - ne) * fx) * row_slope
            # how far past the image's border the point lies (the border's distance is a lower bound)
            past_u = u - min(max(u, 0.0), width)
            past_v = v - min(max(v, 0.0), height)
            beyond = np.sqrt(past_u * past_u + past_v * past_v)
            if beyond > 0.0:
                d_column += past_u / beyond
                d_row += past_v / beyond
            value, slope = _huber(sampled + beyond, huber)
            total += value / count
            pixel_gradient[index, 0] += slope * d_column / count
            pixel_gradient[index, 1] += slope * d_row / count
        for query in range(contour_count):
            index = nearest[frame, query]
            dx = contours[frame, query, 0] - pixels[frame, index, 0]
            dy = contours[frame, query, 1] - pixels[frame, index, 1]
            distance = np.sqrt(dx * dx + dy * dy)
            value, slope = _huber(distance, huber)
            total += value / contour_count
            if distance > 0.0:
                pixel_gradient[index, 0] -= slope * dx / distance / contour_count
                pixel_gradient[index, 1] -= slope * dy / distance / contour_count
        loss[frame] = total
        for index in range(count):  # through the projection to the world point
            gu, gv = pixel_gradient[index, 0], pixel_gradient[index, 1]
            projected_depth = depths[frame, index]
            depth = max(projected_depth, _MIN_DEPTH)
            g_u, g_v = gu / depth, gv / depth
            g_w = -(gu * pixels[frame, index, 0] + gv * pixels[frame, index, 1]) / depth if projected_depth >= _MIN_DEPTH else 0.0
            g_c0 = K[0, 0] * g_u + K[1, 0] * g_v + K[2, 0] * g_w
            g_c1 = K[0, 1] * g_u + K[1, 1] * g_v + K[2, 1] * g_w
            g_c2 = K[0, 2] * g_u + K[1, 2] * g_v + K[2, 2] * g_w
            for k in range(3):
                gradient[frame, index, k] = rotation[0, k] * g_c0 + rotation[1, k] * g_c1 + rotation[2, k] * g_c2
    return loss, gradient


# Side of the grid cells, pixels, in which `_nearest_kernel` files the projected points.
_NEAREST_CELL = 4.0


@numba.njit(cache=True, parallel=True)
def _nearest_kernel(points: np.ndarray, queries: np.ndarray, width: int, height: int, cell: float) -> np.ndarray:
    """(T, M) index of the nearest of `points` (T, P, 2) to each of `queries` (T, M, 2), exactly: the points
    are filed in a grid of `cell`-pixel cells over the image (outside ones in its border cells) and each
    query searches rings of cells outward until no unsearched cell can hold a nearer point."""
    frames, count = points.shape[0], points.shape[1]
    columns, rows = int(width / cell) + 1, int(height / cell) + 1
    nearest = np.empty((frames, queries.shape[1]), np.int64)
    for frame in numba.prange(frames):  # frames are independent
        cell_of = np.empty(count, np.int64)
        starts = np.zeros(columns * rows + 1, np.int64)
        for index in range(count):
            column = min(max(int(points[frame, index, 0] / cell), 0), columns - 1)
            row = min(max(int(points[frame, index, 1] / cell), 0), rows - 1)
            cell_of[index] = row * columns + column
            starts[cell_of[index] + 1] += 1
        for slot in range(columns * rows):
            starts[slot + 1] += starts[slot]
        filled = starts[:-1].copy()
        order = np.empty(count, np.int64)
        for index in range(count):
            order[filled[cell_of[index]]] = index
            filled[cell_of[index]] += 1
        for query in range(queries.shape[1]):
            x, y = queries[frame, query, 0], queries[frame, query, 1]
            home_column = min(max(int(x / cell), 0), columns - 1)
            home_row = min(max(int(y / cell), 0), rows - 1)
            best, best_index = np.inf, -1
            for ring in range(max(columns, rows)):
                for row in range(home_row - ring, home_row + ring + 1):
                    if row < 0 or row >= rows:
                        continue
                    step = 1 if row in (home_row - ring, home_row + ring) else 2 * ring
                    for column in range(home_column - ring, home_column + ring + 1, max(step, 1)):
                        if column < 0 or column >= columns:
                            continue
                        slot = row * columns + column
                        for position in range(starts[slot], starts[slot + 1]):
                            index = order[position]
                            dx, dy = points[frame, index, 0] - x, points[frame, index, 1] - y
                            distance = dx * dx + dy * dy
                            if distance < best:
                                best, best_index = distance, index
                if best_index >= 0 and best <= (ring * cell) ** 2:
                    break
            nearest[frame, query] = best_index
    return nearest


def surface_points(vertices: torch.Tensor, faces: torch.Tensor, count: int) -> torch.Tensor:
    """(count,) indices of template vertices drawn without replacement by their share of the surface area
    (a fixed draw), so dense parts such as the face and the hands do not dominate."""
    corners = vertices[faces]
    areas = 0.5 * torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]).norm(dim=-1)
    vertex_areas = torch.zeros(len(vertices)).index_add_(0, faces.reshape(-1), areas.repeat_interleave(3))
    generator = torch.Generator().manual_seed(0)
    return torch.multinomial(vertex_areas, min(count, int((vertex_areas > 0).sum())), replacement=False, generator=generator)
