"""numba kernels of the EWA projection (gsplat's classic pinhole model) and its analytic backward.

Per Gaussian: p = R m + t (camera frame); means2d = (fx x/z + cx, fy y/z + cy);
A = J R Rq diag(s), with Rq the rotation of the normalised quaternion and J the perspective Jacobian
whose x/z and y/z are clamped to the frustum widened by 15% of the image on each side;
cov2d = A A^T + eps2d I; conic = inverse of cov2d. One `prange` over Gaussians, no temporaries.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

ALPHA_MIN = 1.0 / 255.0
# Contraction, reciprocals and fast library functions (about 10% off both kernels), but no reassociation
# and no NaN/Inf assumptions: results stay within a few ulp of the plain arithmetic.
FASTMATH = {"contract", "arcp", "afn", "nsz"}


@njit(cache=True, inline="always", fastmath=FASTMATH)
def _rotation(qw, qx, qy, qz):
    return (
        1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - qw * qz), 2.0 * (qx * qz + qw * qy),
        2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - qw * qx),
        2.0 * (qx * qz - qw * qy), 2.0 * (qy * qz + qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy),
    )  # fmt: skip


@njit(cache=True, inline="always", fastmath=FASTMATH)
def _clamped(value, low, high):
    """value clamped to [low, high], and whether it was inside."""
    if value < low:
        return low, False
    if value > high:
        return high, False
    return value, True


@njit(cache=True, inline="always", fastmath=FASTMATH)
def _screen_axes(view, q, s, x, y, z, fx, fy, lim):
    """A = J R Rq diag(s) as six numbers (rows of a 2x3), plus the clamped x/z, y/z and flags."""
    qn = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    r = _rotation(q[0] / qn, q[1] / qn, q[2] / qn, q[3] / qn)
    u, inside_x = _clamped(x / z, -lim[0], lim[1])
    v, inside_y = _clamped(y / z, -lim[2], lim[3])
    # J = [[fx/z, 0, -fx u/z], [0, fy/z, -fy v/z]];  T = J R (R = view rotation).
    t0 = (fx * (view[0, 0] - u * view[2, 0]) / z, fx * (view[0, 1] - u * view[2, 1]) / z, fx * (view[0, 2] - u * view[2, 2]) / z)
    t1 = (fy * (view[1, 0] - v * view[2, 0]) / z, fy * (view[1, 1] - v * view[2, 1]) / z, fy * (view[1, 2] - v * view[2, 2]) / z)
    a = (
        (t0[0] * r[0] + t0[1] * r[3] + t0[2] * r[6]) * s[0],
        (t0[0] * r[1] + t0[1] * r[4] + t0[2] * r[7]) * s[1],
        (t0[0] * r[2] + t0[1] * r[5] + t0[2] * r[8]) * s[2],
        (t1[0] * r[0] + t1[1] * r[3] + t1[2] * r[6]) * s[0],
        (t1[0] * r[1] + t1[1] * r[4] + t1[2] * r[7]) * s[1],
        (t1[0] * r[2] + t1[1] * r[5] + t1[2] * r[8]) * s[2],
    )
    return a, r, t0, t1, u, v, inside_x, inside_y, qn


@njit(cache=True, parallel=True, fastmath=FASTMATH)
def project_forward(means, quats, scales, opacities, view, intrinsics, limits, width, height, near, far, eps2d):
    """means (N, 3), quats (N, 4) w x y z, scales (N, 3), opacities (N,); view (4, 4) world->camera;
    intrinsics (fx, fy, cx, cy); limits (4,) clamp of x/z below/above and y/z below/above.

    Returns means2d (N, 2), conics (N, 3), depths (N,), extents (N, 2) and drawn (N,) bool.
    """
    n = means.shape[0]
    dtype = means.dtype
    means2d = np.zeros((n, 2), dtype=dtype)
    conics = np.zeros((n, 3), dtype=dtype)
    depths = np.zeros(n, dtype=dtype)
    extents = np.zeros((n, 2), dtype=dtype)
    drawn = np.zeros(n, dtype=np.bool_)
    for i in prange(n):
        _project_one(
            i, means, quats, scales, opacities, view, intrinsics, limits, width, height, near, far, eps2d,
            means2d, conics, depths, extents, drawn,
        )  # fmt: skip
    return means2d, conics, depths, extents, drawn


@njit(cache=True, fastmath=FASTMATH)
def _project_one(
    i, means, quats, scales, opacities, view, intrinsics, limits, width, height, near, far, eps2d,
    means2d, conics, depths, extents, drawn,
):  # fmt: skip
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    m = means[i]
    x = view[0, 0] * m[0] + view[0, 1] * m[1] + view[0, 2] * m[2] + view[0, 3]
    y = view[1, 0] * m[0] + view[1, 1] * m[1] + view[1, 2] * m[2] + view[1, 3]
    z = view[2, 0] * m[0] + view[2, 1] * m[1] + view[2, 2] * m[2] + view[2, 3]
    depths[i] = z
    if not (near < z < far) or opacities[i] < ALPHA_MIN:
        return
    a = _screen_axes(view, quats[i], scales[i], x, y, z, fx, fy, limits)[0]
    cov_a = a[0] * a[0] + a[1] * a[1] + a[2] * a[2] + eps2d
    cov_b = a[0] * a[3] + a[1] * a[4] + a[2] * a[5]
    cov_c = a[3] * a[3] + a[4] * a[4] + a[5] * a[5] + eps2d
    det = cov_a * cov_c - cov_b * cov_b
    if det <= 0.0:
        return
    u = fx * x / z + cx
    v = fy * y / z + cy
    # Every pixel with alpha >= 1/255 has sigma <= log(255 o); widened like the raster kernels.
    level = 2.0 * math.log(opacities[i] / ALPHA_MIN) * 1.01
    half_x = math.sqrt(level * cov_a) + 0.1
    half_y = math.sqrt(level * cov_c) + 0.1
    means2d[i, 0] = u
    means2d[i, 1] = v
    conics[i, 0] = cov_c / det
    conics[i, 1] = -cov_b / det
    conics[i, 2] = cov_a / det
    extents[i, 0] = half_x
    extents[i, 1] = half_y
    drawn[i] = u + half_x > 0 and u - half_x < width and v + half_y > 0 and v - half_y < height


@njit(cache=True, parallel=True, fastmath=FASTMATH)
def project_backward(
    means, quats, scales, view, intrinsics, limits, conics, drawn,
    grad_means2d, grad_conics, grad_depths,
):  # fmt: skip
    """Gradients w.r.t. means (N, 3), quats (N, 4) and scales (N, 3) of a loss through
    `project_forward`, given dL/d(means2d, conics, depths). Culled Gaussians get depth gradients only.
    """
    n = means.shape[0]
    dtype = means.dtype
    grad_means = np.zeros((n, 3), dtype=dtype)
    grad_quats = np.zeros((n, 4), dtype=dtype)
    grad_scales = np.zeros((n, 3), dtype=dtype)
    for i in prange(n):
        _project_one_backward(
            i, means, quats, scales, view, intrinsics, limits, conics, drawn, grad_means2d, grad_conics,
            grad_depths, grad_means, grad_quats, grad_scales,
        )  # fmt: skip
    return grad_means, grad_quats, grad_scales


@njit(cache=True, fastmath=FASTMATH)
def _project_one_backward(
    i, means, quats, scales, view, intrinsics, limits, conics, drawn, grad_means2d, grad_conics,
    grad_depths, grad_means, grad_quats, grad_scales,
):  # fmt: skip
    fx, fy = intrinsics[0], intrinsics[1]
    m = means[i]
    gz_total = grad_depths[i]
    if not drawn[i]:
        for k in range(3):
            grad_means[i, k] = view[2, k] * gz_total
        return
    x = view[0, 0] * m[0] + view[0, 1] * m[1] + view[0, 2] * m[2] + view[0, 3]
    y = view[1, 0] * m[0] + view[1, 1] * m[1] + view[1, 2] * m[2] + view[1, 3]
    z = view[2, 0] * m[0] + view[2, 1] * m[1] + view[2, 2] * m[2] + view[2, 3]
    s = scales[i]
    q = quats[i]
    a, r, t0, t1, u, v, inside_x, inside_y, qn = _screen_axes(view, q, s, x, y, z, fx, fy, limits)

    # conic = inverse(cov2d): dL/dcov = -Q G_Q Q with G_Q = [[ga, gb/2], [gb/2, gc]].
    qa, qb, qc = conics[i, 0], conics[i, 1], conics[i, 2]
    ga, gb, gc = grad_conics[i, 0], grad_conics[i, 1] * 0.5, grad_conics[i, 2]
    m00 = qa * ga + qb * gb
    m01 = qa * gb + qb * gc
    m10 = qb * ga + qc * gb
    m11 = qb * gb + qc * gc
    s00 = -(m00 * qa + m01 * qb)
    s01 = -(m00 * qb + m01 * qc)
    s11 = -(m10 * qb + m11 * qc)
    # cov2d = A A^T: dL/dA = 2 G A.
    ga_row0 = (2.0 * (s00 * a[0] + s01 * a[3]), 2.0 * (s00 * a[1] + s01 * a[4]), 2.0 * (s00 * a[2] + s01 * a[5]))
    ga_row1 = (2.0 * (s01 * a[0] + s11 * a[3]), 2.0 * (s01 * a[1] + s11 * a[4]), 2.0 * (s01 * a[2] + s11 * a[5]))
    # A = T Rq diag(s): dL/ds_k = sum_j (T Rq)[j, k] dL/dA[j, k]; dL/d(T Rq) = dL/dA diag(s).
    gb0 = (ga_row0[0] * s[0], ga_row0[1] * s[1], ga_row0[2] * s[2])
    gb1 = (ga_row1[0] * s[0], ga_row1[1] * s[1], ga_row1[2] * s[2])
    for k in range(3):
        tr0 = t0[0] * r[k] + t0[1] * r[3 + k] + t0[2] * r[6 + k]
        tr1 = t1[0] * r[k] + t1[1] * r[3 + k] + t1[2] * r[6 + k]
        grad_scales[i, k] = tr0 * ga_row0[k] + tr1 * ga_row1[k]
    # dL/dRq = T^T dL/d(T Rq);  dL/dT = dL/d(T Rq) Rq^T.
    g_r = (
        t0[0] * gb0[0] + t1[0] * gb1[0], t0[0] * gb0[1] + t1[0] * gb1[1], t0[0] * gb0[2] + t1[0] * gb1[2],
        t0[1] * gb0[0] + t1[1] * gb1[0], t0[1] * gb0[1] + t1[1] * gb1[1], t0[1] * gb0[2] + t1[1] * gb1[2],
        t0[2] * gb0[0] + t1[2] * gb1[0], t0[2] * gb0[1] + t1[2] * gb1[1], t0[2] * gb0[2] + t1[2] * gb1[2],
    )  # fmt: skip
    gt0 = (gb0[0] * r[0] + gb0[1] * r[1] + gb0[2] * r[2], gb0[0] * r[3] + gb0[1] * r[4] + gb0[2] * r[5], gb0[0] * r[6] + gb0[1] * r[7] + gb0[2] * r[8])
    gt1 = (gb1[0] * r[0] + gb1[1] * r[1] + gb1[2] * r[2], gb1[0] * r[3] + gb1[1] * r[4] + gb1[2] * r[5], gb1[0] * r[6] + gb1[1] * r[7] + gb1[2] * r[8])
    # Quaternion: through the rotation formula, then the normalisation.
    w_, x_, y_, z_ = q[0] / qn, q[1] / qn, q[2] / qn, q[3] / qn
    gw = 2.0 * (-z_ * g_r[1] + y_ * g_r[2] + z_ * g_r[3] - x_ * g_r[5] - y_ * g_r[6] + x_ * g_r[7])
    gx = 2.0 * (y_ * g_r[1] + z_ * g_r[2] + y_ * g_r[3] - 2.0 * x_ * g_r[4] - w_ * g_r[5] + z_ * g_r[6] + w_ * g_r[7] - 2.0 * x_ * g_r[8])
    gy = 2.0 * (-2.0 * y_ * g_r[0] + x_ * g_r[1] + w_ * g_r[2] + x_ * g_r[3] + z_ * g_r[5] - w_ * g_r[6] + z_ * g_r[7] - 2.0 * y_ * g_r[8])
    gz = 2.0 * (-2.0 * z_ * g_r[0] - w_ * g_r[1] + x_ * g_r[2] + w_ * g_r[3] - 2.0 * z_ * g_r[4] + y_ * g_r[5] + x_ * g_r[6] + y_ * g_r[7])
    dot = gw * w_ + gx * x_ + gy * y_ + gz * z_
    grad_quats[i, 0] = (gw - w_ * dot) / qn
    grad_quats[i, 1] = (gx - x_ * dot) / qn
    grad_quats[i, 2] = (gy - y_ * dot) / qn
    grad_quats[i, 3] = (gz - z_ * dot) / qn
    # T = J R with J = [[fx/z, 0, -fx u/z], [0, fy/z, -fy v/z]]: dL/dJ = dL/dT R^T.
    gj00 = gt0[0] * view[0, 0] + gt0[1] * view[0, 1] + gt0[2] * view[0, 2]
    gj02 = gt0[0] * view[2, 0] + gt0[1] * view[2, 1] + gt0[2] * view[2, 2]
    gj11 = gt1[0] * view[1, 0] + gt1[1] * view[1, 1] + gt1[2] * view[1, 2]
    gj12 = gt1[0] * view[2, 0] + gt1[1] * view[2, 1] + gt1[2] * view[2, 2]
    inv_z = 1.0 / z
    inv_z2 = inv_z * inv_z
    gx_cam = grad_means2d[i, 0] * fx * inv_z
    gy_cam = grad_means2d[i, 1] * fy * inv_z
    gz_total += -(grad_means2d[i, 0] * fx * x + grad_means2d[i, 1] * fy * y) * inv_z2
    gz_total += -gj00 * fx * inv_z2 - gj11 * fy * inv_z2
    # J02 = -fx u / z with u = x/z inside the clamp (else a constant).
    if inside_x:
        gx_cam += -gj02 * fx * inv_z2
        gz_total += 2.0 * gj02 * fx * x * inv_z2 * inv_z
    else:
        gz_total += gj02 * fx * u * inv_z2
    if inside_y:
        gy_cam += -gj12 * fy * inv_z2
        gz_total += 2.0 * gj12 * fy * y * inv_z2 * inv_z
    else:
        gz_total += gj12 * fy * v * inv_z2
    for k in range(3):
        grad_means[i, k] = view[0, k] * gx_cam + view[1, k] * gy_cam + view[2, k] * gz_total
