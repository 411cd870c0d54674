"""SMPL 24-joint kinematics and linear blend skinning of points and Gaussians (batched, differentiable).

Conventions: rotations act on column vectors; quaternions are (w, x, y, z); lengths are metres.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from avatarperfect_cli.body.base import NUM_JOINTS, SMPL_PARENTS
from avatarperfect_cli.rotations import axis_angle_to_matrix

# Polar decomposition: at most this many Newton steps (skinning blends converge in 2 to 6), stopping once
# a step changes no entry by more than the tolerance for the dtype (the error then is about its square).
_POLAR_MAX_ITERATIONS = 20
_POLAR_TOLERANCE = {torch.float32: 1e-4, torch.float64: 1e-8}
# Newton steps use Frobenius-norm scaling only while a step still changes some entry by more than this.
_POLAR_SCALING_CHANGE = 1e-2
# Determinants smaller than this in magnitude are replaced by it (a rank-deficient blend).
_TINY_DETERMINANT = 1e-30
SKINNING_BACKENDS = ("auto", "numba", "torch")
# `skin_points` runs the sparse kernels when no point has more nonzero weights than this (anny's and SMPL's
# templates: at most 7 and 4), and the dense matrix product otherwise.
_SPARSE_JOINTS = 8


@numba.njit(cache=True)
def _hamilton(aw, ax, ay, az, bw, bx, by, bz):
    """Hamilton product a * b of two quaternions given as scalars."""
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


@numba.njit(cache=True)
def _rotation_to_quaternion(r):
    """(3, 3) rotation -> unit quaternion (w, x, y, z), w >= 0.

    Of the four classic formulas (dividing by 4w, 4x, 4y or 4z) it uses the one with the largest
    divisor, at least 2 for a rotation, so every branch is well conditioned.
    """
    t0 = 1.0 + r[0, 0] + r[1, 1] + r[2, 2]
    t1 = 1.0 + r[0, 0] - r[1, 1] - r[2, 2]
    t2 = 1.0 - r[0, 0] + r[1, 1] - r[2, 2]
    t3 = 1.0 - r[0, 0] - r[1, 1] + r[2, 2]
    if t0 >= t1 and t0 >= t2 and t0 >= t3:
        s = 0.5 / np.sqrt(t0)
        w, x, y, z = t0 * s, (r[2, 1] - r[1, 2]) * s, (r[0, 2] - r[2, 0]) * s, (r[1, 0] - r[0, 1]) * s
    elif t1 >= t2 and t1 >= t3:
        s = 0.5 / np.sqrt(t1)
        w, x, y, z = (r[2, 1] - r[1, 2]) * s, t1 * s, (r[1, 0] + r[0, 1]) * s, (r[0, 2] + r[2, 0]) * s
    elif t2 >= t3:
        s = 0.5 / np.sqrt(t2)
        w, x, y, z = (r[0, 2] - r[2, 0]) * s, (r[1, 0] + r[0, 1]) * s, t2 * s, (r[2, 1] + r[1, 2]) * s
    else:
        s = 0.5 / np.sqrt(t3)
        w, x, y, z = (r[1, 0] - r[0, 1]) * s, (r[0, 2] + r[2, 0]) * s, (r[2, 1] + r[1, 2]) * s, t3 * s
    norm = np.sqrt(w * w + x * x + y * y + z * z)
    if w < 0.0:
        norm = -norm
    return w / norm, x / norm, y / norm, z / norm


@numba.njit(cache=True)
def _polar_rotation(m, tolerance, out) -> None:
    """Rotation factor R of the 3x3 block M = m[:3, :3] = R S (S symmetric positive), written to out (3, 3).

    Newton iteration X <- (g X + X^-T / g) / 2 with Frobenius-norm scaling g = sqrt(|X^-1| / |X|);
    X^-T = cofactor(X) / det X. A matrix with negative determinant (a degenerate blend) gets -R.
    """
    a, b, c = float(m[0, 0]), float(m[0, 1]), float(m[0, 2])
    d, e, f = float(m[1, 0]), float(m[1, 1]), float(m[1, 2])
    g, h, i = float(m[2, 0]), float(m[2, 1]), float(m[2, 2])
    det = 1.0
    change = np.inf
    for _ in range(_POLAR_MAX_ITERATIONS):
        # cofactor matrix, rows = cross products of the other two rows
        ca, cb, cc = e * i - f * h, f * g - d * i, d * h - e * g
        cd, ce, cf = c * h - b * i, a * i - c * g, b * g - a * h
        cg, ch, ci = b * f - c * e, c * d - a * f, a * e - b * d
        det = a * ca + b * cb + c * cc
        if abs(det) < _TINY_DETERMINANT:
            det = _TINY_DETERMINANT
        gamma = 1.0
        if change > _POLAR_SCALING_CHANGE:  # scale only far from convergence, where it saves iterations
            norm_sq = a * a + b * b + c * c + d * d + e * e + f * f + g * g + h * h + i * i
            cof_norm_sq = ca * ca + cb * cb + cc * cc + cd * cd + ce * ce + cf * cf + cg * cg + ch * ch + ci * ci
            gamma = np.sqrt(np.sqrt(cof_norm_sq / norm_sq) / abs(det))
        inv = 1.0 / (gamma * det)
        na, nb, nc = 0.5 * (gamma * a + inv * ca), 0.5 * (gamma * b + inv * cb), 0.5 * (gamma * c + inv * cc)
        nd, ne, nf = 0.5 * (gamma * d + inv * cd), 0.5 * (gamma * e + inv * ce), 0.5 * (gamma * f + inv * cf)
        ng, nh, ni = 0.5 * (gamma * g + inv * cg), 0.5 * (gamma * h + inv * ch), 0.5 * (gamma * i + inv * ci)
        change = max(
            abs(na - a), abs(nb - b), abs(nc - c), abs(nd - d), abs(ne - e), abs(nf - f),
            abs(ng - g), abs(nh - h), abs(ni - i),
        )  # fmt: skip
        a, b, c, d, e, f, g, h, i = na, nb, nc, nd, ne, nf, ng, nh, ni
        if change < tolerance:
            break
    sign = 1.0 if det > 0.0 else -1.0
    out[0, 0], out[0, 1], out[0, 2] = sign * a, sign * b, sign * c
    out[1, 0], out[1, 1], out[1, 2] = sign * d, sign * e, sign * f
    out[2, 0], out[2, 1], out[2, 2] = sign * g, sign * h, sign * i


@numba.njit(cache=True, parallel=True)
def _skin_gaussians_forward(
    blended, means, quats, tolerance, rotations, rotation_quats, posed_means, posed_quats
) -> None:
    """Per Gaussian, with blended = [L | t]: posed mean = L mean + t; R = polar rotation of L,
    r = quaternion of R, posed quat = r * quat. One `prange` over the Gaussians."""
    for n in numba.prange(blended.shape[0]):
        m = blended[n]
        mean = means[n]
        for i in range(3):
            posed_means[n, i] = m[i, 0] * mean[0] + m[i, 1] * mean[1] + m[i, 2] * mean[2] + m[i, 3]
        _polar_rotation(m, tolerance, rotations[n])
        w, x, y, z = _rotation_to_quaternion(rotations[n])
        rotation_quats[n, 0], rotation_quats[n, 1], rotation_quats[n, 2], rotation_quats[n, 3] = w, x, y, z
        q = quats[n]
        pw, px, py, pz = _hamilton(w, x, y, z, q[0], q[1], q[2], q[3])
        posed_quats[n, 0], posed_quats[n, 1], posed_quats[n, 2], posed_quats[n, 3] = pw, px, py, pz


@numba.njit(cache=True, parallel=True)
def _skin_gaussians_backward(
    blended, means, quats, rotations, rotation_quats, grad_means, grad_quats, grad_blended, grad_in_means, grad_in_quats
) -> None:
    """Gradients of `_skin_gaussians_forward` w.r.t. blended, means and quats.

    Means: d/dL = g m^T, d/dt = g, d/dmean = L^T g.
    Quats, with r the rotation quaternion and g the gradient of the posed quat: g_r = g * conj(q),
    g_q = conj(r) * g. A body-frame turn dR = R [w]x changes r by r * (0, w) / 2, so the gradient w.r.t. w
    is vec(conj(r) * g_r) / 2. Differentiating L = R S gives (tr(S) I - S) w = vee(R^T dL - dL^T R), hence
    the gradient w.r.t. L is R [h]x with h = (tr(S) I - S)^-1 (gradient w.r.t. w).
    """
    for n in numba.prange(blended.shape[0]):
        m = blended[n]
        gm = grad_means[n]
        mean = means[n]
        for j in range(3):
            grad_in_means[n, j] = m[0, j] * gm[0] + m[1, j] * gm[1] + m[2, j] * gm[2]
        g = grad_quats[n]
        q = quats[n]
        r = rotation_quats[n]
        gq = _hamilton(r[0], -r[1], -r[2], -r[3], g[0], g[1], g[2], g[3])
        grad_in_quats[n, 0], grad_in_quats[n, 1], grad_in_quats[n, 2], grad_in_quats[n, 3] = gq
        grw, grx, gry, grz = _hamilton(g[0], g[1], g[2], g[3], q[0], -q[1], -q[2], -q[3])
        _, ox, oy, oz = _hamilton(r[0], -r[1], -r[2], -r[3], grw, grx, gry, grz)
        ox, oy, oz = 0.5 * ox, 0.5 * oy, 0.5 * oz
        rot = rotations[n]
        # S = R^T L; K = tr(S) I - sym(S), symmetric; h = K^-1 omega by cofactors
        s00 = rot[0, 0] * m[0, 0] + rot[1, 0] * m[1, 0] + rot[2, 0] * m[2, 0]
        s11 = rot[0, 1] * m[0, 1] + rot[1, 1] * m[1, 1] + rot[2, 1] * m[2, 1]
        s22 = rot[0, 2] * m[0, 2] + rot[1, 2] * m[1, 2] + rot[2, 2] * m[2, 2]
        s01 = rot[0, 0] * m[0, 1] + rot[1, 0] * m[1, 1] + rot[2, 0] * m[2, 1]
        s10 = rot[0, 1] * m[0, 0] + rot[1, 1] * m[1, 0] + rot[2, 1] * m[2, 0]
        s02 = rot[0, 0] * m[0, 2] + rot[1, 0] * m[1, 2] + rot[2, 0] * m[2, 2]
        s20 = rot[0, 2] * m[0, 0] + rot[1, 2] * m[1, 0] + rot[2, 2] * m[2, 0]
        s12 = rot[0, 1] * m[0, 2] + rot[1, 1] * m[1, 2] + rot[2, 1] * m[2, 2]
        s21 = rot[0, 2] * m[0, 1] + rot[1, 2] * m[1, 1] + rot[2, 2] * m[2, 1]
        trace = s00 + s11 + s22
        k00, k11, k22 = trace - s00, trace - s11, trace - s22
        k01, k02, k12 = -0.5 * (s01 + s10), -0.5 * (s02 + s20), -0.5 * (s12 + s21)
        c00, c11, c22 = k11 * k22 - k12 * k12, k00 * k22 - k02 * k02, k00 * k11 - k01 * k01
        c01, c02, c12 = k02 * k12 - k01 * k22, k01 * k12 - k02 * k11, k01 * k02 - k00 * k12
        det = k00 * c00 + k01 * c01 + k02 * c02
        if abs(det) < _TINY_DETERMINANT:
            det = np.inf
        hx = (c00 * ox + c01 * oy + c02 * oz) / det
        hy = (c01 * ox + c11 * oy + c12 * oz) / det
        hz = (c02 * ox + c12 * oy + c22 * oz) / det
        for i in range(3):
            grad_blended[n, i, 0] = rot[i, 1] * hz - rot[i, 2] * hy + gm[i] * mean[0]
            grad_blended[n, i, 1] = rot[i, 2] * hx - rot[i, 0] * hz + gm[i] * mean[1]
            grad_blended[n, i, 2] = rot[i, 0] * hy - rot[i, 1] * hx + gm[i] * mean[2]
            grad_blended[n, i, 3] = gm[i]


@numba.njit(cache=True)
def _rotations_to_quaternions(rotations, quats) -> None:
    for n in range(rotations.shape[0]):
        quats[n, 0], quats[n, 1], quats[n, 2], quats[n, 3] = _rotation_to_quaternion(rotations[n])


def _to_numpy(tensor: torch.Tensor) -> np.ndarray:
    return tensor.detach().cpu().contiguous().numpy()


def matrix_to_quaternion(rotations: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions w x y z with w >= 0 (not differentiable)."""
    flat = _to_numpy(rotations).reshape(-1, 3, 3)
    quats = np.empty((flat.shape[0], 4), dtype=flat.dtype)
    _rotations_to_quaternions(flat, quats)
    return torch.from_numpy(quats).to(rotations.device).reshape(rotations.shape[:-2] + (4,))


class _SkinGaussians(torch.autograd.Function):
    """(blended (N, 3, 4), means (N, 3), quats (N, 4)) -> posed means (N, 3), posed quats (N, 4), on the CPU
    with numba (tensors elsewhere make a round trip)."""

    @staticmethod
    def forward(ctx, blended: torch.Tensor, means: torch.Tensor, quats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        arrays = (_to_numpy(blended), _to_numpy(means), _to_numpy(quats))
        n = arrays[0].shape[0]
        rotations = np.empty((n, 3, 3), dtype=arrays[0].dtype)
        rotation_quats = np.empty((n, 4), dtype=arrays[0].dtype)
        posed_means = np.empty((n, 3), dtype=arrays[1].dtype)
        posed_quats = np.empty((n, 4), dtype=arrays[2].dtype)
        tolerance = _POLAR_TOLERANCE[blended.dtype]
        _skin_gaussians_forward(*arrays, tolerance, rotations, rotation_quats, posed_means, posed_quats)
        ctx.arrays = (*arrays, rotations, rotation_quats)
        return torch.from_numpy(posed_means).to(means.device), torch.from_numpy(posed_quats).to(quats.device)

    @staticmethod
    def backward(ctx, grad_means: torch.Tensor, grad_quats: torch.Tensor) -> tuple[torch.Tensor, ...]:
        blended, means, quats, rotations, rotation_quats = ctx.arrays
        grads = (np.empty_like(blended), np.empty_like(means), np.empty_like(quats))
        _skin_gaussians_backward(
            blended, means, quats, rotations, rotation_quats, _to_numpy(grad_means), _to_numpy(grad_quats), *grads
        )
        device = grad_means.device
        return tuple(torch.from_numpy(grad).to(device) for grad in grads)


# The torch path (any device, CUDA in practice) works on batched (N, 3, 3) and (N, 4, 4) tensors inside one
# autograd Function with the numba kernel's closed-form backward: on a GPU the time of this path is the
# count of kernel launches (a few dozen here; per-entry formulas under autograd took about a thousand).

# table[k] lists, for the quaternion branch k, which of (t0..t3, (R - R^T) flattened, (R + R^T) flattened)
# make up 2 sqrt(t_k) times the quaternion (the numba `_rotation_to_quaternion`'s four formulas)
_QUATERNION_TABLE = ((0, 11, 6, 7), (11, 1, 16, 15), (6, 16, 2, 20), (7, 15, 20, 3))
# L(a) b = a * b (Hamilton) with L(a)[i, j] = sign[i][j] * a[index[i][j]]
_HAMILTON_INDEX = ((0, 1, 2, 3), (1, 0, 3, 2), (2, 3, 0, 1), (3, 2, 1, 0))
_HAMILTON_SIGN = ((1, -1, -1, -1), (1, 1, -1, 1), (1, 1, 1, -1), (1, -1, 1, 1))
_CONJUGATE = (1, -1, -1, -1)
_CONSTANTS: dict[tuple[torch.device, torch.dtype], tuple[torch.Tensor, ...]] = {}


def _constants(device: torch.device, dtype: torch.dtype) -> tuple[torch.Tensor, ...]:
    """The tables above as tensors on `device` (made once per device and dtype: no copies per call)."""
    key = (device, dtype)
    if key not in _CONSTANTS:
        _CONSTANTS[key] = (
            torch.tensor(_QUATERNION_TABLE, device=device),
            torch.tensor(_HAMILTON_INDEX, device=device),
            torch.tensor(_HAMILTON_SIGN, dtype=dtype, device=device),
            torch.tensor(_CONJUGATE, dtype=dtype, device=device),
        )
    return _CONSTANTS[key]


def _cofactors_batched(m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 3, 3) -> cofactor matrices (N, 3, 3) (rows: cross products of the other two rows) and
    determinants (N,); M^-T = cofactors / det."""
    cofactors = torch.linalg.cross(m.roll(-1, dims=1), m.roll(-2, dims=1), dim=-1)
    return cofactors, (m[:, 0] * cofactors[:, 0]).sum(-1)


def _polar_rotation_batched(linear: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) M = R S (S symmetric positive) -> rotation factors R (N, 3, 3); the numba `_polar_rotation`
    batched: scaled Newton steps X <- (g X + X^-T / g) / 2, each matrix scaled while its last step changed
    an entry by more than _POLAR_SCALING_CHANGE, until no entry of any matrix changes by more than the
    dtype's tolerance; a negative determinant gives -R."""
    tolerance = _POLAR_TOLERANCE[linear.dtype]
    x = linear.contiguous()
    change = torch.full(x.shape[:1], torch.inf, dtype=x.dtype, device=x.device)
    det = torch.ones_like(change)
    largest_change = math.inf
    for _ in range(_POLAR_MAX_ITERATIONS):
        cofactors, det = _cofactors_batched(x)
        det = torch.where(det.abs() < _TINY_DETERMINANT, _TINY_DETERMINANT, det)
        if largest_change > _POLAR_SCALING_CHANGE:  # else every gamma is 1: skip the launches
            ratio = torch.sqrt(cofactors.square().sum((1, 2)) / x.square().sum((1, 2)))
            gamma = torch.where(change > _POLAR_SCALING_CHANGE, torch.sqrt(ratio / det.abs()), 1.0)
            step = torch.addcmul(0.5 * gamma[:, None, None] * x, cofactors, (0.5 / (gamma * det))[:, None, None])
        else:
            step = torch.addcmul(0.5 * x, cofactors, (0.5 / det)[:, None, None])
        change = (step - x).abs().amax((1, 2))
        x = step
        largest_change = float(change.max()) if change.numel() else 0.0  # the one wait for the GPU per step
        if largest_change < tolerance:
            break
    return x * det.sign()[:, None, None]  # det is never 0 here


def _rotation_to_quaternion_batched(rotations: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) rotations -> (N, 4) unit quaternions w x y z, w >= 0, by the numba `_rotation_to_quaternion`'s
    branch: the formula of the largest t_k (the first on ties)."""
    r = rotations
    r00, r11, r22 = r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]
    t = torch.stack([1 + r00 + r11 + r22, 1 + r00 - r11 - r22, 1 - r00 + r11 - r22, 1 - r00 - r11 + r22], dim=-1)
    source = torch.cat([t, (r - r.mT).flatten(1), (r + r.mT).flatten(1)], dim=1)
    row = source.gather(1, table[t.argmax(dim=1)])
    sign = torch.where(row[:, :1] < 0, -1.0, 1.0).to(r.dtype)
    return row * (sign / torch.sqrt((row * row).sum(1, keepdim=True)))


def _hamilton_matrices(a: torch.Tensor, index: torch.Tensor, sign: torch.Tensor) -> torch.Tensor:
    """(N, 4) quaternions a -> (N, 4, 4) matrices L(a) with L(a) b = a * b."""
    return a[:, index] * sign


class _SkinGaussiansTorch(torch.autograd.Function):
    """`_SkinGaussians` in torch on any device: (blended (N, 3, 4), means (N, 3), quats (N, 4)) -> posed means
    (N, 3), posed quats (N, 4), with the numba kernel's closed-form backward (`_skin_gaussians_backward`)."""

    @staticmethod
    def forward(ctx, blended: torch.Tensor, means: torch.Tensor, quats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        table, index, sign, conjugate = _constants(blended.device, blended.dtype)
        linear = blended[..., :3]
        posed_means = torch.baddbmm(blended[..., 3:], linear, means[..., None])[..., 0]
        rotations = _polar_rotation_batched(linear)
        rotation_quats = _rotation_to_quaternion_batched(rotations, table)
        posed_quats = torch.bmm(_hamilton_matrices(rotation_quats, index, sign), quats.to(blended.dtype)[..., None])[..., 0]
        ctx.save_for_backward(linear, means, quats, rotations, rotation_quats)
        return posed_means.to(means.dtype), posed_quats.to(quats.dtype)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_means: torch.Tensor, grad_quats: torch.Tensor) -> tuple[torch.Tensor, ...]:
        linear, means, quats, rotations, rotation_quats = ctx.saved_tensors
        _, index, sign, conjugate = _constants(linear.device, linear.dtype)
        gm = torch.zeros_like(means) if grad_means is None else grad_means.to(linear.dtype)
        g = torch.zeros_like(quats) if grad_quats is None else grad_quats.to(linear.dtype)
        grad_in_means = torch.bmm(linear.mT, gm[..., None])[..., 0]
        # posed = r * q: dq = conj(r) * g; dr = g * conj(q); the turn w (dR = R [w]x) gets vec(conj(r) * dr) / 2
        by_conjugate_rotation = _hamilton_matrices(rotation_quats * conjugate, index, sign)
        grad_in_quats = torch.bmm(by_conjugate_rotation, g[..., None])[..., 0]
        conjugate_quats = quats.to(linear.dtype) * conjugate
        grad_rotation_quats = torch.bmm(_hamilton_matrices(g, index, sign), conjugate_quats[..., None])
        omega = 0.5 * torch.bmm(by_conjugate_rotation, grad_rotation_quats)[:, 1:, 0]
        # L = R S: (tr(S) I - sym S) h = omega, and the gradient w.r.t. L is R [h]x (row i: r_i x h)
        stretch = torch.bmm(rotations.mT, linear)
        trace = stretch.diagonal(dim1=1, dim2=2).sum(-1)
        eye = torch.eye(3, dtype=linear.dtype, device=linear.device)
        k = trace[:, None, None] * eye - 0.5 * (stretch + stretch.mT)
        k_cofactors, k_det = _cofactors_batched(k)  # symmetric
        k_det = torch.where(k_det.abs() < _TINY_DETERMINANT, torch.inf, k_det)
        h = torch.bmm(k_cofactors, omega[..., None])[..., 0] / k_det[:, None]
        grad_linear = torch.linalg.cross(rotations, h[:, None, :].expand_as(rotations), dim=-1)
        grad_linear = torch.baddbmm(grad_linear, gm[..., None], means.to(linear.dtype)[:, None, :])
        grad_blended = torch.cat([grad_linear, gm[..., None]], dim=-1)
        return grad_blended, grad_in_means.to(means.dtype), grad_in_quats.to(quats.dtype)


def _skin_blended_torch(
    blended: torch.Tensor, means: torch.Tensor, quats: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """`_SkinGaussians` in torch on any device: (N, 3, 4), (N, 3), (N, 4) -> posed means (N, 3), posed quats (N, 4)."""
    return _SkinGaussiansTorch.apply(blended, means, quats)


def _tree_levels(parents: tuple[int, ...]) -> tuple[list[list[int]], list[list[int]], list[int]]:
    """Joints grouped by depth: each level's joints, each joint's parent's position in the level before,
    and every joint's position in the levels' concatenation."""
    depth = [0] * len(parents)
    for joint, parent in enumerate(parents):
        depth[joint] = 0 if parent < 0 else depth[parent] + 1
    levels = [[j for j in range(len(parents)) if depth[j] == d] for d in range(max(depth) + 1)]
    parent_slots = [[levels[d - 1].index(parents[j]) for j in level] if d else [] for d, level in enumerate(levels)]
    order = [j for level in levels for j in level]
    return levels, parent_slots, [order.index(j) for j in range(len(parents))]


_LEVELS, _PARENT_SLOTS, _LEVEL_ORDER_INVERSE = _tree_levels(SMPL_PARENTS)


def forward_kinematics(body_pose: torch.Tensor, rest_joints: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
    """SMPL forward kinematics.

    body_pose:   (B, 24, 3) axis-angle local joint rotations; joint 0 is the global orientation about the root
    rest_joints: (24, 3) joint positions in the canonical pose, metres
    transl:      (B, 3) global translation, metres
    returns      (B, 24, 4, 4) transforms mapping canonical points to posed world points
                 (each joint's world transform times the inverse of its rest transform)

    Each transform is its parent's composed with the joint's rotation about its rest position,
    A_j = A_parent [R_j | J_j - R_j J_j], so a joint with zero rotation and identity ancestors is exactly I.
    Computed one tree level at a time.
    """
    local_rotations = axis_angle_to_matrix(body_pose)
    # translation of "rotate by R_j about J_j": J_j - R_j J_j
    pivots = rest_joints - (local_rotations @ rest_joints[..., None])[..., 0]
    rotations = [local_rotations[:, :1]]
    translations = [pivots[:, :1] + transl[:, None]]
    for joints, slots in zip(_LEVELS[1:], _PARENT_SLOTS[1:]):
        parent_rotations = rotations[-1][:, slots]
        rotations.append(parent_rotations @ local_rotations[:, joints])
        translations.append(translations[-1][:, slots] + (parent_rotations @ pivots[:, joints, :, None])[..., 0])
    rotation = torch.cat(rotations, dim=1)[:, _LEVEL_ORDER_INVERSE]
    translation = torch.cat(translations, dim=1)[:, _LEVEL_ORDER_INVERSE]
    top = torch.cat([rotation, translation[..., None]], dim=-1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def posed_joints(transforms: torch.Tensor, rest_joints: torch.Tensor) -> torch.Tensor:
    """(..., 24, 3) world joint positions, metres: `rest_joints` (24, 3) moved by their own transforms
    (..., 24, 4, 4) from `forward_kinematics`."""
    return (transforms[..., :3, :3] @ rest_joints[..., None])[..., 0] + transforms[..., :3, 3]


def blend_transforms(weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """Per-point blended affine transforms.

    weights:    (N, 24) skinning weights
    transforms: (..., 24, 4, 4) joint transforms
    returns     (..., N, 3, 4) the weighted sums of the joints' top 3x4 blocks
    """
    batch, points = transforms.shape[:-3], weights.shape[0]
    # one (N, 24) x (24, batch * 12) product: a broadcast batched matmul can be far slower on the CPU
    blocks = transforms[..., :3, :].reshape(-1, NUM_JOINTS, 12).transpose(0, 1).reshape(NUM_JOINTS, -1)
    blended = (weights @ blocks).reshape(points, -1, 3, 4).transpose(0, 1)
    return blended.reshape(batch + (points, 3, 4))


def skin_points(points: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """Linear blend skinning. points: (N, 3) canonical; weights: (N, 24); transforms: (..., 24, 4, 4) -> (..., N, 3).

    On the CPU, with weights that need no gradient and at most `_SPARSE_JOINTS` nonzero weights per point
    (skinning templates), numba kernels visit each point's few joints (`_SkinPoints`). Otherwise
    sum_j w_nj A_j [p_n; 1], bilinear in the weights and the homogeneous point, is one (N, 24 * 4) x
    (24 * 4, batch * 3) matrix product, forward and backward (`skin_points_product`; blending the transforms
    first and then taking one 3x4 matrix-vector product per point costs a batched product of N tiny matrices
    each way)."""
    on_cpu = points.device.type == "cpu" and transforms.device.type == "cpu"
    if on_cpu and not weights.requires_grad and points.dtype == transforms.dtype == weights.dtype:
        slots = int((weights != 0).sum(dim=1).max()) if len(weights) else 0
        if slots <= _SPARSE_JOINTS:
            joints = weights.abs().topk(max(slots, 1), dim=1).indices  # largest first: a zero ends a point's list
            return _SkinPoints.apply(points, transforms, joints.int(), weights.gather(1, joints))
    return skin_points_product(points, weights, transforms)


def skin_points_product(points: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """`skin_points` as one matrix product on any device, differentiable in all three inputs."""
    homogeneous = torch.cat([points, torch.ones_like(points[:, :1])], dim=1)
    lifted = (weights[:, :, None] * homogeneous[:, None, :]).reshape(len(points), NUM_JOINTS * 4)
    blocks = transforms[..., :3, :].reshape(-1, NUM_JOINTS, 3, 4).permute(1, 3, 0, 2).reshape(NUM_JOINTS * 4, -1)
    posed = (lifted @ blocks).reshape(len(points), -1, 3)
    return posed.transpose(0, 1).reshape(transforms.shape[:-3] + (len(points), 3))


@numba.njit(cache=True, parallel=True)
def _skin_points_forward(points, joints, values, transforms, posed) -> None:
    """posed[b, n] = sum_k values[n, k] (transforms[b, joints[n, k]] [points[n]; 1]) over a point's nonzero
    weights (`values` ordered largest first, so the first zero ends the list). One `prange` over the batch."""
    for b in numba.prange(transforms.shape[0]):
        for n in range(points.shape[0]):
            x, y, z = points[n, 0], points[n, 1], points[n, 2]
            o0 = o1 = o2 = 0.0
            for k in range(joints.shape[1]):
                w = values[n, k]
                if w == 0.0:
                    break
                a = transforms[b, joints[n, k]]
                o0 += w * (a[0, 0] * x + a[0, 1] * y + a[0, 2] * z + a[0, 3])
                o1 += w * (a[1, 0] * x + a[1, 1] * y + a[1, 2] * z + a[1, 3])
                o2 += w * (a[2, 0] * x + a[2, 1] * y + a[2, 2] * z + a[2, 3])
            posed[b, n, 0], posed[b, n, 1], posed[b, n, 2] = o0, o1, o2


@numba.njit(cache=True, parallel=True)
def _skin_points_transforms_backward(points, joints, values, grad_posed, grad_transforms) -> None:
    """grad_transforms[b, j, r] += w_nj grad_posed[b, n, r] [points[n]; 1] (zeroed beforehand; the bottom rows
    stay zero). One `prange` over the batch: each writes its own transforms."""
    for b in numba.prange(grad_posed.shape[0]):
        for n in range(points.shape[0]):
            x, y, z = points[n, 0], points[n, 1], points[n, 2]
            for k in range(joints.shape[1]):
                w = values[n, k]
                if w == 0.0:
                    break
                g = grad_transforms[b, joints[n, k]]
                for r in range(3):
                    wg = w * grad_posed[b, n, r]
                    g[r, 0] += wg * x
                    g[r, 1] += wg * y
                    g[r, 2] += wg * z
                    g[r, 3] += wg


@numba.njit(cache=True, parallel=True)
def _skin_points_points_backward(joints, values, transforms, grad_posed, grad_points) -> None:
    """grad_points[n] = sum over the batch of L_bn^T grad_posed[b, n], L_bn the blend of the point's joints'
    3x3 blocks. One `prange` over the points: each sums over the batch on its own."""
    for n in numba.prange(grad_points.shape[0]):
        s0 = s1 = s2 = 0.0
        for b in range(transforms.shape[0]):
            g0, g1, g2 = grad_posed[b, n, 0], grad_posed[b, n, 1], grad_posed[b, n, 2]
            for k in range(joints.shape[1]):
                w = values[n, k]
                if w == 0.0:
                    break
                a = transforms[b, joints[n, k]]
                s0 += w * (a[0, 0] * g0 + a[1, 0] * g1 + a[2, 0] * g2)
                s1 += w * (a[0, 1] * g0 + a[1, 1] * g1 + a[2, 1] * g2)
                s2 += w * (a[0, 2] * g0 + a[1, 2] * g1 + a[2, 2] * g2)
        grad_points[n, 0], grad_points[n, 1], grad_points[n, 2] = s0, s1, s2


class _SkinPoints(torch.autograd.Function):
    """(points (N, 3), transforms (..., 24, 4, 4), joints (N, K) int32, values (N, K)) -> posed (..., N, 3):
    linear blend skinning over each point's K largest weights, on the CPU with numba; gradients for the points
    and the transforms."""

    @staticmethod
    def forward(ctx, points: torch.Tensor, transforms: torch.Tensor, joints: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
        arrays = (_to_numpy(points), _to_numpy(joints), _to_numpy(values), _to_numpy(transforms).reshape(-1, NUM_JOINTS, 4, 4))
        posed = np.empty((arrays[3].shape[0], len(points), 3), dtype=arrays[0].dtype)
        _skin_points_forward(*arrays, posed)
        ctx.arrays, ctx.batch = arrays, transforms.shape[:-3]
        return torch.from_numpy(posed).reshape(ctx.batch + (len(points), 3))

    @staticmethod
    def backward(ctx, grad_posed: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        points, joints, values, transforms = ctx.arrays
        grad = _to_numpy(grad_posed).reshape(transforms.shape[0], len(points), 3)
        grad_points = grad_transforms = None
        if ctx.needs_input_grad[0]:
            grad_points = np.empty_like(points)
            _skin_points_points_backward(joints, values, transforms, grad, grad_points)
            grad_points = torch.from_numpy(grad_points)
        if ctx.needs_input_grad[1]:
            grad_transforms = np.zeros_like(transforms)
            _skin_points_transforms_backward(points, joints, values, grad, grad_transforms)
            grad_transforms = torch.from_numpy(grad_transforms).reshape(ctx.batch + (NUM_JOINTS, 4, 4))
        return grad_points, grad_transforms, None, None


def skin_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    weights: torch.Tensor,
    transforms: torch.Tensor,
    *,
    backend: str = "auto",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Linear blend skinning of Gaussian centres and orientations.

    means:      (N, 3) canonical centres, metres
    quats:      (N, 4) canonical orientations w x y z (any norm; the norm is kept)
    weights:    (N, 24) skinning weights
    transforms: (24, 4, 4) joint transforms from `forward_kinematics`
    returns     posed means (N, 3) and quats (N, 4): each orientation is turned by the rotation factor
                of its blended 3x3 matrix (polar decomposition)
    backend:    "numba" (CPU kernel with a closed-form backward), "torch" (any device, autograd) or "auto"
                (numba for CPU tensors, torch otherwise); float32 or float64
    """
    if backend not in SKINNING_BACKENDS:
        raise ValueError(f"unknown skinning backend {backend!r}; choose one of {', '.join(SKINNING_BACKENDS)}")
    blended = blend_transforms(weights, transforms)
    if backend == "numba" or (backend == "auto" and means.device.type == "cpu"):
        return _SkinGaussians.apply(blended, means, quats)
    return _skin_blended_torch(blended, means, quats)
