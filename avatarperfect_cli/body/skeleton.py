"""SMPL 24-joint kinematics and linear blend skinning of points and Gaussians (batched, differentiable).

Conventions: rotations act on column vectors; quaternions are (w, x, y, z); lengths are metres.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from avatarperfect_cli.body.base import NUM_JOINTS, SMPL_PARENTS

# Below this squared angle (rad^2) Rodrigues' coefficients use their Taylor series.
_SMALL_ANGLE_SQ = 1e-6
# Polar decomposition: at most this many Newton steps (skinning blends converge in 2 to 6), stopping once
# a step changes no entry by more than the tolerance for the dtype (the error then is about its square).
_POLAR_MAX_ITERATIONS = 20
_POLAR_TOLERANCE = {torch.float32: 1e-4, torch.float64: 1e-8}
# Newton steps use Frobenius-norm scaling only while a step still changes some entry by more than this.
_POLAR_SCALING_CHANGE = 1e-2
# Determinants smaller than this in magnitude are replaced by it (a rank-deficient blend).
_TINY_DETERMINANT = 1e-30
SKINNING_BACKENDS = ("auto", "numba", "torch")


def _skew(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) vectors -> (..., 3, 3) cross-product matrices [v]x."""
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(v.shape + (3,))


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula. axis_angle: (..., 3) axis times angle in radians -> (..., 3, 3) rotations.

    R = I + a K + b K^2 with K = [axis_angle]x, a = sin(t)/t, b = (1 - cos t)/t^2; a and b use their
    Taylor series near t = 0, so values and gradients are exact there.
    """
    angle_sq = (axis_angle * axis_angle).sum(-1)
    small = angle_sq < _SMALL_ANGLE_SQ
    angle = torch.sqrt(torch.where(small, torch.ones_like(angle_sq), angle_sq))
    a = torch.where(small, 1.0 - angle_sq / 6.0 + angle_sq * angle_sq / 120.0, torch.sin(angle) / angle)
    half_sinc = torch.sin(0.5 * angle) / angle  # (1 - cos t) / t^2 = 2 (sin(t/2) / t)^2, no cancellation
    b = torch.where(small, 0.5 - angle_sq / 24.0 + angle_sq * angle_sq / 720.0, 2.0 * half_sinc * half_sinc)
    k = _skew(axis_angle)
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def quaternion_to_matrix(quats: torch.Tensor) -> torch.Tensor:
    """(..., 4) quaternions w x y z, any non-zero norm -> (..., 3, 3) rotation matrices."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(quats.shape[:-1] + (3, 3))  # fmt: skip


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


# The torch path (any device) stores 3x3 matrices entries first, (3, 3, N): every operation then runs on
# contiguous length-N vectors (on the CPU, ops on (N, 3, 3) such as linalg.cross are ~10x slower).


def _cross(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Cross products of (3, ...) vectors (components first)."""
    return torch.stack([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]])


def _cofactors(m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(3, 3, ...) entries first -> cofactor matrices (3, 3, ...) (rows: cross products of the other two rows)
    and determinants (...); M^-T = cofactors / det."""
    cofactors = torch.stack([_cross(m[1], m[2]), _cross(m[2], m[0]), _cross(m[0], m[1])])
    return cofactors, (m[0] * cofactors[0]).sum(0)


@torch.no_grad()
def _polar_rotation_torch(matrices: torch.Tensor) -> torch.Tensor:
    """(3, 3, ...) entries first, M = R S (S symmetric positive) -> rotation factors R (3, 3, ...); no gradient.

    The numba `_polar_rotation` batched: scaled Newton steps X <- (g X + X^-T / g) / 2 until no entry of
    any matrix changes by more than the dtype's tolerance; a negative determinant gives -R.
    """
    tolerance = _POLAR_TOLERANCE[matrices.dtype]
    x = matrices.contiguous()
    change = torch.full(x.shape[2:], torch.inf, dtype=x.dtype, device=x.device)
    for _ in range(_POLAR_MAX_ITERATIONS):
        cofactors, det = _cofactors(x)
        det = torch.where(det.abs() < _TINY_DETERMINANT, _TINY_DETERMINANT, det)
        frobenius_ratio = torch.sqrt(cofactors.square().sum((0, 1)) / x.square().sum((0, 1)))
        gamma = torch.where(change > _POLAR_SCALING_CHANGE, torch.sqrt(frobenius_ratio / det.abs()), 1.0)
        step = 0.5 * (gamma * x + cofactors / (gamma * det))
        change = (step - x).abs().amax((0, 1))
        x = step
        if not change.numel() or change.max() < tolerance:
            break
    return x * det.sign()  # det is never 0 here


def _differentiable_polar_rotation(linear: torch.Tensor) -> torch.Tensor:
    """(3, 3, ...) entries first, M -> its rotation factor R (3, 3, ...) with the exact derivative for autograd.

    R comes from the Newton iteration without a graph. Differentiating M = R S gives dR = R [w]x with
    (tr(S) I - sym S) w = vee(R^T dM - dM^T R), so R + R [w]x - stopgrad(R [w]x), w computed from the live M,
    has R's value and R's derivative (the numba backward's formula) without differentiating the iteration.
    """
    rotation = _polar_rotation_torch(linear.detach())
    if not linear.requires_grad:
        return rotation
    stretch = (rotation[:, :, None] * linear[:, None, :]).sum(0)  # R^T M, with the graph
    fixed = stretch.detach()
    trace = fixed[0, 0] + fixed[1, 1] + fixed[2, 2]
    eye = torch.eye(3, dtype=linear.dtype, device=linear.device).reshape((3, 3) + (1,) * (linear.dim() - 2))
    k_cofactors, k_det = _cofactors(eye * trace - 0.5 * (fixed + fixed.transpose(0, 1)))  # symmetric
    k_det = torch.where(k_det.abs() < _TINY_DETERMINANT, torch.inf, k_det)
    vee = torch.stack([stretch[2, 1] - stretch[1, 2], stretch[0, 2] - stretch[2, 0], stretch[1, 0] - stretch[0, 1]])
    omega = (k_cofactors * vee[None]).sum(1) / k_det
    turn = torch.stack([_cross(row, omega) for row in rotation])  # row i of R [w]x is r_i x w
    return rotation + (turn - turn.detach())


def _rotation_to_quaternion_torch(rotations: torch.Tensor) -> torch.Tensor:
    """(3, 3, ...) entries first, rotations -> (4, ...) unit quaternions w x y z, w >= 0; differentiable.

    The numba `_rotation_to_quaternion` batched: row k of the symmetric 4x4 table below is 2 sqrt(t_k) times
    the quaternion; it uses the row with the largest diagonal t_k (the first on ties), picked by 0/1 masks
    (a gather or argmax across the 4 rows is far slower on the CPU).
    """
    r = rotations
    r00, r11, r22 = r[0, 0], r[1, 1], r[2, 2]
    t0, t1, t2, t3 = 1 + r00 + r11 + r22, 1 + r00 - r11 - r22, 1 - r00 + r11 - r22, 1 - r00 - r11 + r22
    xw, yw, zw = r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]
    xy, xz, yz = r[1, 0] + r[0, 1], r[0, 2] + r[2, 0], r[2, 1] + r[1, 2]
    first = (t0 >= t1) & (t0 >= t2) & (t0 >= t3)
    second = ~first & (t1 >= t2) & (t1 >= t3)
    third = ~first & ~second & (t2 >= t3)
    fourth = ~(first | second | third)
    table = [(t0, xw, yw, zw), (xw, t1, xy, xz), (yw, xy, t2, yz), (zw, xz, yz, t3)]
    masks = [mask.to(r.dtype) for mask in (first, second, third, fourth)]
    row = torch.stack([sum(mask * entries[c] for mask, entries in zip(masks, table)) for c in range(4)])
    sign_over_norm = torch.where(row[0] < 0, -1.0, 1.0).to(r.dtype) / torch.sqrt((row * row).sum(0))
    return row * sign_over_norm


def _quaternion_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton products a * b of (..., 4) quaternions w x y z."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def _skin_blended_torch(
    blended: torch.Tensor, means: torch.Tensor, quats: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """`_SkinGaussians` in torch on any device, differentiable by autograd: (N, 3, 4), (N, 3), (N, 4) ->
    posed means (N, 3), posed quats (N, 4)."""
    posed_means = (blended[..., :3] * means[..., None, :]).sum(-1) + blended[..., 3]
    rotation_quats = _rotation_to_quaternion_torch(_differentiable_polar_rotation(blended[..., :3].permute(1, 2, 0)))
    return posed_means, _quaternion_multiply(rotation_quats.mT, quats)


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
    """Linear blend skinning. points: (N, 3) canonical; weights: (N, 24); transforms: (B, 24, 4, 4) -> (B, N, 3)."""
    homogeneous = torch.cat([points, torch.ones_like(points[:, :1])], dim=1)
    return torch.einsum("...nij,nj->...ni", blend_transforms(weights, transforms), homogeneous)


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
