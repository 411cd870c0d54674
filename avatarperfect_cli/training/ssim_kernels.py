"""numba kernels of SSIM on the CPU: the SSIM map of two images and its gradient, 11-tap window.

Images are (H, L) arrays of rows with the channels interleaved (L = W * C, the memory layout of an
(H, W, C) image), so a horizontal tap moves by C elements and every inner loop runs over a contiguous
row. The window is a symmetric 11-tap 1D filter applied along rows then columns, zero padded ('same'
size). Only pixels at least `border` pixels from every edge enter the SSIM mean; `border` = 0 is
3DGS's zero-padded SSIM, `border` = 5 the 'valid' one.

Each thread owns a block of output rows and keeps the row-filtered rows it needs in a ring of 11
slots (plus an all-zero slot for rows outside the image), so no full-size intermediate is stored.

Gradient. With the filtered moments mx = G*x, my = G*y, Sxx = G*x², Syy = G*y², Sxy = G*xy and
A1 = 2 mx my + C1, A2 = 2 (Sxy - mx my) + C2, B1 = mx² + my² + C1, B2 = Sxx - mx² + Syy - my² + C2,
S = A1 A2 / (B1 B2) has
    dS/dmx = 2 my (A2 - A1) / (B1 B2) + 2 mx S (1/B2 - 1/B1)    (dS/dmy: swap mx and my)
    dS/dSxx = dS/dSyy = -S / B2,    dS/dSxy = 2 A1 / (B1 B2).
The symmetric zero-padded filter is its own adjoint, so with the per-pixel derivative maps D:
    dL/dx = G*D_mx + 2 x G*D_Sxx + y G*D_Sxy,    dL/dy = G*D_my + 2 y G*D_Syy + x G*D_Sxy.
Derivative map order: 0 dS/dSxx (= dS/dSyy), 1 dS/dSxy, 2 dS/dmx, 3 dS/dmy.

Performance notes (measured): inner loops index 1D views with a `range(n)` counter only, because
`row[j + offset]` with a run-time offset makes numba emit a negative-index check that stops LLVM
from vectorising (4x slower); the 11 taps are summed in registers (one store per output) rather
than accumulated tap by tap (1.7x).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

WINDOW = 11
_RADIUS = WINDOW // 2


@njit(inline="always")
def _filter11(r0, r1, r2, r3, r4, r5, r6, r7, r8, r9, r10, taps, out):
    """out[j] = sum_k taps[k] * r_k[j] for a symmetric 11-tap window, all 11 terms in registers."""
    t0, t1, t2, t3, t4, t5 = taps[0], taps[1], taps[2], taps[3], taps[4], taps[5]
    for j in range(out.shape[0]):
        out[j] = (
            t5 * r5[j]
            + t4 * (r4[j] + r6[j])
            + t3 * (r3[j] + r7[j])
            + t2 * (r2[j] + r8[j])
            + t1 * (r1[j] + r9[j])
            + t0 * (r0[j] + r10[j])
        )


@njit(inline="always")
def _filter_padded_row(padded, taps, step, out):
    """out (L,) <- the zero-padded row filter of a row stored with 5 * step zeros each side."""
    n = out.shape[0]
    _filter11(
        padded[0:n], padded[step : step + n], padded[2 * step : 2 * step + n],
        padded[3 * step : 3 * step + n], padded[4 * step : 4 * step + n], padded[5 * step : 5 * step + n],
        padded[6 * step : 6 * step + n], padded[7 * step : 7 * step + n], padded[8 * step : 8 * step + n],
        padded[9 * step : 9 * step + n], padded[10 * step : 10 * step + n], taps, out,
    )  # fmt: skip


@njit(inline="always")
def _row_moments(x_row, y_row, taps, step, padded, out):
    """out (5, L) <- x, y, x*x, y*y, x*y of one image row, each filtered along the row.

    padded: (5, L + 10 * step) scratch whose margins are zero.
    """
    length = x_row.shape[0]
    pad = _RADIUS * step
    p0, p1, p2 = padded[0, pad : pad + length], padded[1, pad : pad + length], padded[2, pad : pad + length]
    p3, p4 = padded[3, pad : pad + length], padded[4, pad : pad + length]
    for j in range(length):
        a, b = x_row[j], y_row[j]
        p0[j] = a
        p1[j] = b
        p2[j] = a * a
        p3[j] = b * b
        p4[j] = a * b
    for m in range(5):
        _filter_padded_row(padded[m], taps, step, out[m])


@njit(inline="always")
def _row_maps(maps, row, taps, step, padded, out):
    """out (M, L) <- row `row` of the (M, H, L) maps, each filtered along the row (padded as above)."""
    length = maps.shape[2]
    pad = _RADIUS * step
    for m in range(maps.shape[0]):
        padded[m, pad : pad + length] = maps[m, row]
        _filter_padded_row(padded[m], taps, step, out[m])


@njit(inline="always")
def _slot(row, height):
    """Ring slot of a row-filtered image row; rows outside [0, height) use the all-zero last slot."""
    return row % WINDOW if 0 <= row < height else WINDOW


@njit(inline="always")
def _column(ring, taps, i, height, out):
    """out (M, L) <- row i filtered along the columns, from the ring (12, M, L) of row-filtered rows.

    Row r sits in slot r % 11; slot 11 is all zero and stands for the rows outside [0, height).
    """
    s0, s1, s2 = _slot(i - 5, height), _slot(i - 4, height), _slot(i - 3, height)
    s3, s4, s5 = _slot(i - 2, height), _slot(i - 1, height), _slot(i, height)
    s6, s7, s8 = _slot(i + 1, height), _slot(i + 2, height), _slot(i + 3, height)
    s9, s10 = _slot(i + 4, height), _slot(i + 5, height)
    for m in range(out.shape[0]):
        _filter11(
            ring[s0, m], ring[s1, m], ring[s2, m], ring[s3, m], ring[s4, m], ring[s5, m],
            ring[s6, m], ring[s7, m], ring[s8, m], ring[s9, m], ring[s10, m], taps, out[m],
        )  # fmt: skip


@njit(inline="always")
def _ssim_terms(mx, my, sxx, syy, sxy, c1, c2):
    """SSIM = a1 a2 / (b1 b2) from the local means and (uncentred) second moments."""
    return 2.0 * mx * my + c1, 2.0 * (sxy - mx * my) + c2, mx * mx + my * my + c1, sxx - mx * mx + syy - my * my + c2


@njit(inline="always")
def _ssim_row(moments, c1, c2, first, last, derivatives, i):
    """Sum of SSIM over columns [first, last) of one row of filtered moments (5, L).

    Writes the row's derivative maps into derivatives[:, i] (nothing when there are none).
    """
    mxs, mys = moments[0, first:last], moments[1, first:last]
    sxxs, syys, sxys = moments[2, first:last], moments[3, first:last], moments[4, first:last]
    total = 0.0
    if derivatives.shape[0] == 0:
        for j in range(last - first):
            mx, my = mxs[j], mys[j]
            a1, a2, b1, b2 = _ssim_terms(mx, my, sxxs[j], syys[j], sxys[j], c1, c2)
            total += a1 * a2 / (b1 * b2)
        return total
    d_sq, d_sxy, d_mx = derivatives[0, i, first:last], derivatives[1, i, first:last], derivatives[2, i, first:last]
    for j in range(last - first):
        mx, my = mxs[j], mys[j]
        a1, a2, b1, b2 = _ssim_terms(mx, my, sxxs[j], syys[j], sxys[j], c1, c2)
        inv_b = 1.0 / (b1 * b2)
        value = a1 * a2 * inv_b
        total += value
        d_sq[j] = -value / b2
        d_sxy[j] = 2.0 * a1 * inv_b
        d_mx[j] = 2.0 * (my * (a2 - a1) * inv_b + mx * value * (1.0 / b2 - 1.0 / b1))
    if derivatives.shape[0] > 3:
        d_my = derivatives[3, i, first:last]
        for j in range(last - first):
            mx, my = mxs[j], mys[j]
            a1, a2, b1, b2 = _ssim_terms(mx, my, sxxs[j], syys[j], sxys[j], c1, c2)
            inv_b = 1.0 / (b1 * b2)
            d_my[j] = 2.0 * (mx * (a2 - a1) * inv_b + my * a1 * a2 * inv_b * (1.0 / b2 - 1.0 / b1))
    return total


@njit(parallel=True, fastmath=True, cache=True)
def ssim_forward(x, y, taps, c1, c2, border, step, derivative_maps, blocks):
    """Per-row sums of the SSIM map, and its derivative maps.

    x, y:            (H, L) images, L = W * C with C = step channels interleaved
    taps:            (11,) symmetric 1D window
    border:          pixels skipped at every edge (0: 'same', 5: 'valid')
    derivative_maps: 0 (no gradient), 3 (gradient of x) or 4 (of x and y)
    blocks:          row blocks run in parallel (the thread count)
    Returns row_sums (H,) float64, zero outside `border`, and derivatives (derivative_maps, H, L),
    zero outside `border` (order in the module docstring).
    """
    height, length = x.shape
    first, last = border * step, length - border * step
    row_sums = np.zeros(height, dtype=np.float64)
    derivatives = np.zeros((derivative_maps, height, length), dtype=x.dtype)
    rows = height - 2 * border
    for block in prange(blocks):
        start, stop = border + rows * block // blocks, border + rows * (block + 1) // blocks
        ring = np.empty((WINDOW + 1, 5, length), dtype=x.dtype)
        ring[WINDOW] = 0.0
        padded = np.zeros((5, length + 2 * _RADIUS * step), dtype=x.dtype)
        moments = np.empty((5, length), dtype=x.dtype)
        next_row = max(start - _RADIUS, 0)
        for i in range(start, stop):
            while next_row <= min(i + _RADIUS, height - 1):
                _row_moments(x[next_row], y[next_row], taps, step, padded, ring[next_row % WINDOW])
                next_row += 1
            _column(ring, taps, i, height, moments)
            row_sums[i] = _ssim_row(moments, c1, c2, first, last, derivatives, i)
    return row_sums, derivatives


@njit(parallel=True, fastmath=True, cache=True)
def ssim_backward(derivatives, taps, x, y, step, scale, blocks):
    """dL/dx and, with 4 derivative maps, dL/dy, from the derivative maps (M, H, L) of `ssim_forward`.

    x, y: (H, L) the inputs; scale: dL/d(mean SSIM) divided by the number of averaged values.
    Returns grad_x (H, L) and grad_y (H, L) (zeros when M = 3).
    """
    count, height, length = derivatives.shape
    grad_x = np.empty_like(x)
    grad_y = np.zeros_like(y)
    for block in prange(blocks):
        start, stop = height * block // blocks, height * (block + 1) // blocks
        ring = np.empty((WINDOW + 1, count, length), dtype=x.dtype)
        ring[WINDOW] = 0.0
        padded = np.zeros((count, length + 2 * _RADIUS * step), dtype=x.dtype)
        filtered = np.empty((count, length), dtype=x.dtype)
        next_row = max(start - _RADIUS, 0)
        for i in range(start, stop):
            while next_row <= min(i + _RADIUS, height - 1):
                _row_maps(derivatives, next_row, taps, step, padded, ring[next_row % WINDOW])
                next_row += 1
            _column(ring, taps, i, height, filtered)
            f_sq, f_sxy, f_mx = filtered[0], filtered[1], filtered[2]
            xs, ys, gx = x[i], y[i], grad_x[i]
            for j in range(length):
                gx[j] = scale * (f_mx[j] + 2.0 * xs[j] * f_sq[j] + ys[j] * f_sxy[j])
            if count > 3:
                f_my, gy = filtered[3], grad_y[i]
                for j in range(length):
                    gy[j] = scale * (f_my[j] + 2.0 * ys[j] * f_sq[j] + xs[j] * f_sxy[j])
    return grad_x, grad_y
