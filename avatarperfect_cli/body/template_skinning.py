"""A body template's skinning weights at any canonical point: the weights of its nearest vertices.

An avatar's Gaussians start on the template's vertices with the template's weights, then move and learn
their own. Learned from a monocular video's few poses, the weights fit those poses and go wrong where
the video saw little (the armpits and crotch); the template's weights at a Gaussian's canonical position
are what the body model says it should follow. On `default` seed 0,
giving every Gaussian of the initial avatar the template's weights raised held-out PSNR by 0.40 dB (the
crotch's error fell by 41%) and cost the training frames 1.8 dB: other weights move a Gaussian in the
video's poses too. Refine moves its canonical mean and orientation with the weights so that it stays
where the video saw it (`reanchored_means`, `reanchored_quats`: held out +1.17 dB, training frames -0.005 dB on that
avatar); where the video's poses bend the body too unlike a rigid turn for that,
it moves the weights only as far as keeps the Gaussian near where the video put it (`bounded_pull_shares`).

The weight at a point blends its K_NEAREST nearest template vertices with the Gaussian falloff
exp(-(d / (d_nearest + FALLOFF_FLOOR))^2), so a point on a vertex takes mostly that vertex's weights and
a point between vertices a smooth mix. The nearest vertices come from an exact grid search (numba).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from avatarperfect_cli.body.base import BodyTemplate
from avatarperfect_cli.body.skeleton import matrix_to_quaternion, skin_gaussians, skin_points
from avatarperfect_cli.rotations import quaternion_to_matrix

K_NEAREST = 8
FALLOFF_FLOOR = 5e-3  # metres; a point closer than this to its nearest vertex blends like one this far
GRID_CELL = 0.02  # metres; about the spacing of anny's and SMPL's vertices


def template_skin_weights(template: BodyTemplate, points: torch.Tensor, k: int = K_NEAREST) -> torch.Tensor:
    """(N, 24) skinning weights (rows sum to 1) of the template at canonical `points` (N, 3), metres:
    its `k` nearest vertices' weights blended by distance (see the module docstring); float32, on
    `points`' device."""
    vertices = template.vertices.detach().cpu().double().numpy()
    if not 1 <= k <= len(vertices):
        raise ValueError(f"k must be in [1, {len(vertices)}], got {k}")
    query = points.detach().cpu().double().numpy()
    distances, indices = nearest_vertices(query, vertices, k)
    blend = np.exp(-((distances / (distances[:, :1] + FALLOFF_FLOOR)) ** 2))
    blend /= blend.sum(axis=1, keepdims=True)
    weights = np.einsum("nk,nkj->nj", blend, template.weights.detach().cpu().double().numpy()[indices])
    return torch.from_numpy(weights / weights.sum(axis=1, keepdims=True)).float().to(points.device)


def bounded_pull_shares(
    means: torch.Tensor, weights: torch.Tensor, target: torch.Tensor, transforms: torch.Tensor, max_share: float,
    max_shift: float, poses_per_batch: int = 8,
) -> torch.Tensor:
    """(N,) how far each point's skinning weights may move from `weights` toward `target` (0: stay, 1: the
    target's) so that its skinned position moves at most `max_shift` metres in every pose:
    min(max_share, max_shift / d), d its largest displacement over the poses when moved the whole way.
    Skinning is linear in the weights, so a share s moves the point by exactly s times that displacement.

    means: (N, 3) canonical, metres; weights, target: (N, 24) (rows sum to 1); transforms: (T, 24, 4, 4)
    the poses' joint transforms (`forward_kinematics`); float32 result on `means`' device."""
    with torch.no_grad():
        change, shift = target - weights, weights.new_zeros(len(means))
        for batch in transforms.split(poses_per_batch):
            shift = torch.maximum(shift, skin_points(means, change, batch).norm(dim=-1).amax(dim=0))
    return (max_shift / shift.clamp_min(torch.finfo(shift.dtype).tiny)).clamp(max=max_share).float()


def reanchored_means(
    means: torch.Tensor, weights: torch.Tensor, new_weights: torch.Tensor, transforms: torch.Tensor, points_per_batch: int = 32768
) -> torch.Tensor:
    """(N, 3) canonical means that, skinned with `new_weights`, land where `means` skinned with `weights` land
    in the poses `transforms`, by least squares over the poses: sum_t |B'_t m' - B_t m|^2, B_t and B'_t the
    blended transforms of the old and new weights in pose t, one 3 x 3 solve per point (float64). Exact
    where the poses differ only by a rigid motion of the whole body (a turntable).

    The normal equations need the poses only through their sums over t of R_tk^T R_tj and R_tk^T t_tj for
    every pair of joints (R, t: a joint transform's rotation and translation), so the cost does not grow
    with the number of poses.
    means: (N, 3) canonical, metres; weights, new_weights: (N, 24), rows summing to 1; transforms:
    (T, 24, 4, 4) the poses' joint transforms (`forward_kinematics`)."""
    with torch.no_grad():
        linear, offset = transforms.double()[..., :3, :3], transforms.double()[..., :3, 3]
        joints = linear.shape[1]
        turn_pairs = torch.einsum("tkba,tjbc->kjac", linear, linear).reshape(joints, joints * 9)
        shift_pairs = torch.einsum("tkba,tjb->kja", linear, offset).reshape(joints, joints * 3)
        solved = []
        for chunk_means, chunk_weights, chunk_new in zip(
            means.double().split(points_per_batch), weights.double().split(points_per_batch), new_weights.double().split(points_per_batch)
        ):
            # per point and joint j: sum_k w'_k sum_t R_tk^T R_tj (3 x 3) and sum_k w'_k sum_t R_tk^T t_tj (3)
            turned = (chunk_new @ turn_pairs).reshape(-1, joints, 3, 3)
            shifted = (chunk_new @ shift_pairs).reshape(-1, joints, 3)
            normal = torch.einsum("nj,njab->nab", chunk_new, turned)
            posed_turn = torch.einsum("nj,njab->nab", chunk_weights, turned)
            rhs = (posed_turn @ chunk_means[:, :, None])[..., 0] + torch.einsum("nj,nja->na", chunk_weights - chunk_new, shifted)
            solved.append(torch.linalg.solve(normal, rhs))
        return torch.cat(solved).to(means.dtype)


def reanchored_quats(
    means: torch.Tensor, quats: torch.Tensor, weights: torch.Tensor, new_weights: torch.Tensor, transforms: torch.Tensor,
    poses: int = 10,
) -> torch.Tensor:
    """(N, 4) canonical quats (w x y z, the norms of `quats` kept) that, skinned with `new_weights`, turn like
    `quats` skinned with `weights` in the poses `transforms`: the mean relative rotation over `poses` of
    them, evenly spaced, projected to a rotation. Exact where the poses differ only by a rigid motion.
    means: (N, 3) canonical, metres, where the skinning's rotations are read; the rest as `reanchored_means`."""
    with torch.no_grad():
        means64, weights64, new_weights64 = means.double(), weights.double(), new_weights.double()
        no_turn = means64.new_tensor([1.0, 0.0, 0.0, 0.0]).expand(len(means), 4)
        turn = means64.new_zeros(len(means), 3, 3)
        chosen = torch.linspace(0, len(transforms) - 1, min(poses, len(transforms))).round().long()
        for pose in transforms.double()[chosen]:
            _, old_quats = skin_gaussians(means64, quats.double(), weights64, pose)
            _, new_turn = skin_gaussians(means64, no_turn, new_weights64, pose)
            turn += quaternion_to_matrix(new_turn).mT @ quaternion_to_matrix(old_quats)
        left, _, right = torch.linalg.svd(turn)
        flip = torch.ones_like(means64)
        flip[:, 2] = torch.linalg.det(left @ right).sign()
        unit = matrix_to_quaternion(left @ (flip[..., None] * right))
        return (unit * quats.double().norm(dim=-1, keepdim=True)).to(quats.dtype)


def largest_shift(
    means: torch.Tensor, weights: torch.Tensor, new_means: torch.Tensor, new_weights: torch.Tensor, transforms: torch.Tensor,
    poses_per_batch: int = 32,
) -> torch.Tensor:
    """(N,) metres: each point's largest distance over the poses `transforms` between `means` skinned with
    `weights` and `new_means` skinned with `new_weights` (float64 inside, `means`' dtype out). The
    difference is one skinning of the per-joint vectors (w'_j m' - w_j m, w'_j - w_j): one product for a
    batch of poses."""
    with torch.no_grad():
        joints = weights.shape[1]
        moved_by_joint = torch.cat(
            [
                new_weights.double()[..., None] * new_means.double()[:, None] - weights.double()[..., None] * means.double()[:, None],
                (new_weights.double() - weights.double())[..., None],
            ],
            dim=-1,
        ).reshape(len(means), joints * 4)
        shift = means.new_zeros(len(means), dtype=torch.float64)
        for batch in transforms.double().split(poses_per_batch):
            blocks = batch[..., :3, :].permute(1, 3, 0, 2).reshape(joints * 4, -1)  # (joint, column) x (pose, row)
            moved = (moved_by_joint @ blocks).reshape(len(means), -1, 3)
            shift = torch.maximum(shift, moved.norm(dim=-1).amax(dim=1))
        return shift.to(means.dtype)


def nearest_vertices(points: np.ndarray, vertices: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The k nearest `vertices` (V, 3) of each of `points` (N, 3): distances (N, k) ascending and their
    indices (N, k) int64. Exact: a uniform grid of GRID_CELL cells over the vertices, searched in growing
    shells of cells around each point's (clamped) cell until no unsearched cell can hold a nearer vertex."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    origin = vertices.min(axis=0)
    dims = np.floor((vertices.max(axis=0) - origin) / GRID_CELL).astype(np.int64) + 1
    coords = np.floor((vertices - origin) / GRID_CELL).astype(np.int64)
    cells = (coords[:, 0] * dims[1] + coords[:, 1]) * dims[2] + coords[:, 2]
    order = np.argsort(cells, kind="stable")
    starts = np.searchsorted(cells[order], np.arange(int(np.prod(dims)) + 1))
    distances = np.empty((len(points), k))
    indices = np.empty((len(points), k), dtype=np.int64)
    _grid_knn(points, vertices, origin, GRID_CELL, dims, order, starts, distances, indices)
    return distances, indices


@numba.njit(cache=True)
def _visit_cell(point, vertices, order, start, stop, best_d, best_i) -> None:
    """Insert the vertices order[start:stop] into the ascending k-nearest lists best_d, best_i."""
    k = best_d.shape[0]
    for s in range(start, stop):
        v = order[s]
        dx = vertices[v, 0] - point[0]
        dy = vertices[v, 1] - point[1]
        dz = vertices[v, 2] - point[2]
        d = math.sqrt(dx * dx + dy * dy + dz * dz)
        if d < best_d[k - 1]:
            slot = k - 1
            while slot > 0 and best_d[slot - 1] > d:
                best_d[slot] = best_d[slot - 1]
                best_i[slot] = best_i[slot - 1]
                slot -= 1
            best_d[slot] = d
            best_i[slot] = v


@numba.njit(cache=True, parallel=True)
def _grid_knn(points, vertices, origin, cell, dims, order, starts, out_distances, out_indices) -> None:
    """Per point: visit the cells on the surface of the cube of Chebyshev radius 0, 1, 2, ... around its
    cell (clamped into the grid), keeping the k nearest vertices. After radius s, an unvisited vertex lies
    beyond one of the cube's faces that is inside the grid, so at least that face's distance away; the
    search stops once the k-th distance is at most the nearest such face's (or no such face is left)."""
    k = out_distances.shape[1]
    for n in numba.prange(points.shape[0]):
        point = points[n]
        best_d = np.full(k, np.inf)
        best_i = np.full(k, -1, dtype=np.int64)
        c0 = min(max(int(math.floor((point[0] - origin[0]) / cell)), 0), dims[0] - 1)
        c1 = min(max(int(math.floor((point[1] - origin[1]) / cell)), 0), dims[1] - 1)
        c2 = min(max(int(math.floor((point[2] - origin[2]) / cell)), 0), dims[2] - 1)
        shell = 0
        while True:
            for i in range(max(c0 - shell, 0), min(c0 + shell, dims[0] - 1) + 1):
                for j in range(max(c1 - shell, 0), min(c1 + shell, dims[1] - 1) + 1):
                    flat = (i * dims[1] + j) * dims[2]
                    if abs(i - c0) == shell or abs(j - c1) == shell:  # a face of the cube: the whole column
                        for m in range(max(c2 - shell, 0), min(c2 + shell, dims[2] - 1) + 1):
                            _visit_cell(point, vertices, order, starts[flat + m], starts[flat + m + 1], best_d, best_i)
                    else:  # inside the faces: only the column's two ends are new
                        if c2 - shell >= 0:
                            m = c2 - shell
                            _visit_cell(point, vertices, order, starts[flat + m], starts[flat + m + 1], best_d, best_i)
                        if shell > 0 and c2 + shell <= dims[2] - 1:
                            m = c2 + shell
                            _visit_cell(point, vertices, order, starts[flat + m], starts[flat + m + 1], best_d, best_i)
            bound = np.inf
            if c0 - shell > 0:
                bound = min(bound, point[0] - (origin[0] + (c0 - shell) * cell))
            if c0 + shell < dims[0] - 1:
                bound = min(bound, origin[0] + (c0 + shell + 1) * cell - point[0])
            if c1 - shell > 0:
                bound = min(bound, point[1] - (origin[1] + (c1 - shell) * cell))
            if c1 + shell < dims[1] - 1:
                bound = min(bound, origin[1] + (c1 + shell + 1) * cell - point[1])
            if c2 - shell > 0:
                bound = min(bound, point[2] - (origin[2] + (c2 - shell) * cell))
            if c2 + shell < dims[2] - 1:
                bound = min(bound, origin[2] + (c2 + shell + 1) * cell - point[2])
            if best_d[k - 1] <= bound or bound == np.inf:
                break
            shell += 1
        out_distances[n] = best_d
        out_indices[n] = best_i
