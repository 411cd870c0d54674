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
    """(..., 3) world points, metres -> (..., 2) pixel coordinates (x right, y down; pixel centres at +0.5).

    Written out per coordinate: a (..., 3) x (3, 3) matmul is several times slower on the CPU, forward and
    backward, and the fits project every step."""
    rotation, translation, K = camera.world_to_camera[:3, :3], camera.world_to_camera[:3, 3], camera.K
    x, y, z = points.unbind(-1)
    in_camera = [x * row[0] + y * row[1] + z * row[2] + shift for row, shift in zip(rotation, translation)]
    u, v, depth = (in_camera[0] * row[0] + in_camera[1] * row[1] + in_camera[2] * row[2] for row in K)
    depth = depth.clamp_min(1e-3)
    return torch.stack([u / depth, v / depth], dim=-1)


def huber_distance(distance: torch.Tensor, delta: float) -> torch.Tensor:
    return torch.where(distance < delta, 0.5 * distance * distance / delta, distance - 0.5 * delta)


def silhouette_loss(posed: torch.Tensor, data: Silhouettes, huber: float) -> torch.Tensor:
    """(T,) each compared frame's mean outside distance of its posed points plus mean coverage distance of
    its contour pixels, pixels. posed: (T, P, 3) template points posed by the frames' poses, world frame, metres."""
    pixels = project(posed, data.camera)  # (T, P, 2)
    size = torch.tensor([data.camera.width, data.camera.height], dtype=pixels.dtype)
    grid = (2.0 * pixels / size - 1.0)[:, :, None]  # (T, P, 1, 2)
    outside = F.grid_sample(data.outside, grid, mode="bilinear", padding_mode="border", align_corners=False)
    # beyond the image the border's distance is a lower bound: add how far past the border a point is
    beyond = (pixels - pixels.clamp(torch.zeros_like(size), size)).norm(dim=-1)
    x, y = pixels.unbind(-1)
    top, bottom, left, right = (data.cut[:, None, side] for side in range(4))
    unseen = (y < 0) & top | (y > size[1]) & bottom | (x < 0) & left | (x > size[0]) & right
    outside_loss = huber_distance(torch.where(unseen, 0.0, outside[:, 0, :, 0] + beyond), huber).mean(dim=1)
    nearest = _nearest_points(pixels, data)
    coverage = (data.contours - pixels.gather(1, nearest[..., None].expand(-1, -1, 2))).norm(dim=-1)
    return outside_loss + huber_distance(coverage, huber).mean(dim=1)


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


def _nearest_points(pixels: torch.Tensor, data: Silhouettes) -> torch.Tensor:
    """(T, M) index of the projected point (pixels (T, P, 2)) nearest to each contour pixel."""
    points = pixels.detach().numpy().astype(np.float64)
    queries = data.contours.numpy().astype(np.float64)
    return torch.from_numpy(_nearest_kernel(points, queries, data.camera.width, data.camera.height, _NEAREST_CELL))



def surface_points(vertices: torch.Tensor, faces: torch.Tensor, count: int) -> torch.Tensor:
    """(count,) indices of template vertices drawn without replacement by their share of the surface area
    (a fixed draw), so dense parts such as the face and the hands do not dominate."""
    corners = vertices[faces]
    areas = 0.5 * torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]).norm(dim=-1)
    vertex_areas = torch.zeros(len(vertices)).index_add_(0, faces.reshape(-1), areas.repeat_interleave(3))
    generator = torch.Generator().manual_seed(0)
    return torch.multinomial(vertex_areas, min(count, int((vertex_areas > 0).sum())), replacement=False, generator=generator)
