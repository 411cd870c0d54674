"""numba kernels of the CPU rasterizer: tile binning, front-to-back compositing and its backward.

Conventions follow gsplat: pixel centres at +0.5; alpha = min(0.999, o * exp(-sigma)) with
sigma = 0.5 * (a dx^2 + c dy^2) + b dx dy, (dx, dy) = mean2d - pixel centre and (a, b, c) the conic
(inverse 2D covariance); contributions with alpha < 1/255 are skipped; a pixel stops before its
transmittance would fall to 1e-4 or below (that Gaussian is excluded).

Each tile keeps its Gaussians in depth order. A tile loops over its Gaussians and visits, row by row,
only the pixels inside the Gaussian's ellipse {sigma <= log(255 o)} (outside it alpha < 1/255), which
is exact and several times faster than testing every pixel against every Gaussian.

Each tile-Gaussian pair gets one packed row (`pack_intersections`) in the tiles' compositing order, so
the compositing loops of both passes read memory in sequence rather than gather every Gaussian's fields
from six arrays (about 9% off the forward kernel, gather included).

Tiles are dealt round-robin, by decreasing cost, to one `prange` iteration per thread: numba's static
split of a plain `prange` over tiles leaves one thread idle on the busy tiles of a human figure.
Gradients and visibility go to per-intersection records (one row per tile-Gaussian pair), reduced per
Gaussian afterwards, so no atomics are needed.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
TRANSMITTANCE_MIN = 1e-4
# The ellipse used to pick pixels is widened a little so that rounding never drops a pixel whose
# alpha reaches 1/255; every visited pixel is still tested exactly.
_SPAN_SCALE = 1.01
_SPAN_PAD = 0.01

# Floating-point licences for the compositing loops: contraction, reassociation and reciprocals, but
# not the no-NaN/no-Inf assumptions (the alpha tests must stay exact comparisons).
FASTMATH = {"contract", "reassoc", "arcp", "nsz", "afn"}

# Per-intersection gradient record columns; colour gradients follow.
G_MEAN_X, G_MEAN_Y, G_CONIC_A, G_CONIC_B, G_CONIC_C, G_OPACITY, G_FEATURES = 0, 1, 2, 3, 4, 5, 6


# Columns of `gaussian_spans`: per-Gaussian constants of the ellipse {sigma <= level} that bounds the
# pixels worth visiting, level = log(opacity * 255) widened by _SPAN_SCALE and _SPAN_PAD.
S_HALF_HEIGHT, S_INV_A, S_NEG_DET, S_TWO_A_LEVEL = 0, 1, 2, 3


@njit(cache=True, parallel=True)
def gaussian_spans(conics, opacities, drawn):
    """(N, 4) span constants: half height of the ellipse (pixels), 1/a, b^2 - ac and 2 a level."""
    spans = np.zeros((conics.shape[0], 4), dtype=conics.dtype)
    for g in prange(conics.shape[0]):
        if not drawn[g]:
            continue
        a, b, c = conics[g, 0], conics[g, 1], conics[g, 2]
        level = _SPAN_SCALE * math.log(opacities[g] / ALPHA_MIN) + _SPAN_PAD
        spans[g, S_HALF_HEIGHT] = math.sqrt(2.0 * level * a / (a * c - b * b))
        spans[g, S_INV_A] = 1.0 / a
        spans[g, S_NEG_DET] = b * b - a * c
        spans[g, S_TWO_A_LEVEL] = 2.0 * a * level
    return spans


@njit(cache=True, inline="always")
def _row_range(my, span, y_first, y_last):
    """Pixel rows [first, last] of the Gaussian's span ellipse, clipped to [y_first, y_last]."""
    half_height = span[S_HALF_HEIGHT]
    return max(math.ceil(my - half_height - 0.5), y_first), min(math.floor(my + half_height - 0.5), y_last)


@njit(cache=True, inline="always")
def _row_span(mx, dy, b, span, x_first, x_last):
    """Pixel columns [lo, hi] of the row at vertical offset dy = my - (y + 0.5) inside the
    Gaussian's span ellipse, clipped to [x_first, x_last]."""
    disc = dy * dy * span[S_NEG_DET] + span[S_TWO_A_LEVEL]
    if disc < 0.0:
        return 1, 0
    root = math.sqrt(disc)
    lo = math.ceil(mx + (b * dy - root) * span[S_INV_A] - 0.5)
    hi = math.floor(mx + (b * dy + root) * span[S_INV_A] - 0.5)
    return max(lo, x_first), min(hi, x_last)


@njit(cache=True, inline="always")
def _compositing_constants(like):
    """0.5, 1, ALPHA_MAX, ALPHA_MIN, TRANSMITTANCE_MIN and 0 in the dtype of the array `like`. A Python
    float is float64 to numba, and one in an expression lifts a float32 kernel's arithmetic (its exp too)
    to float64: typed constants take about 12% off the forward kernel and 15% off the backward."""
    values = np.empty(6, dtype=like.dtype)
    values[0], values[1], values[2], values[3], values[4], values[5] = 0.5, 1.0, ALPHA_MAX, ALPHA_MIN, TRANSMITTANCE_MIN, 0.0
    return values[0], values[1], values[2], values[3], values[4], values[5]


@njit(cache=True, inline="always")
def _pixel_centres(first, out):
    """out[i] = first + i + 0.5: the centres of a tile's pixel columns or rows, in out's dtype."""
    for i in range(out.shape[0]):
        out[i] = first + i + 0.5


# Columns of `pack_intersections`' rows: the Gaussian's 2D mean, conic, opacity, span constants
# (`gaussian_spans`) and then its features.
P_MEAN_X, P_MEAN_Y, P_CONIC_A, P_CONIC_B, P_CONIC_C, P_OPACITY, P_SPAN, P_FEATURES = 0, 1, 2, 3, 4, 5, 6, 10


RADIX_BITS = 11


@njit(cache=True)
def depth_order(depth_keys, drawn, key_bits):
    """Drawn Gaussians' indices by increasing depth, ties kept in index order (stable LSD radix sort).

    depth_keys: (N,) the depths' IEEE bit patterns as unsigned integers of `key_bits` bits; for the
    positive depths of drawn Gaussians they order exactly like the depths.
    """
    order = np.nonzero(drawn)[0]
    scratch = np.empty_like(order)
    counts = np.empty((1 << RADIX_BITS) + 1, dtype=np.int64)
    for shift in range(0, key_bits, RADIX_BITS):
        counts[:] = 0
        for i in range(order.shape[0]):
            counts[((depth_keys[order[i]] >> shift) & ((1 << RADIX_BITS) - 1)) + 1] += 1
        if counts.max() == order.shape[0]:
            continue  # every key has the same digit here
        counts = np.cumsum(counts)
        for i in range(order.shape[0]):
            digit = (depth_keys[order[i]] >> shift) & ((1 << RADIX_BITS) - 1)
            scratch[counts[digit]] = order[i]
            counts[digit] += 1
        order, scratch = scratch, order
    return order


@njit(cache=True, parallel=True)
def bin_gaussians(means2d, extents, depth_keys, key_bits, drawn, width, height, tile_size, region, n_threads):
    """Assign Gaussians to the tiles their ellipse bounding box touches, depth-sorted per tile.

    means2d: (N, 2) pixels; extents: (N, 2) half-widths of the bounding box, pixels;
    depth_keys, key_bits: camera z as for `depth_order`; drawn: (N,) bool;
    region: (row_start, row_stop, col_start, col_stop) pixels; only tiles it touches get Gaussians;
    n_threads: the chunks the work is cut into (numba.get_num_threads(); the result does not depend on it).
    Returns tile_offsets (n_tiles + 1,) int64 and tile_gaussians (n_intersections,) int32, where the
    Gaussians of tile t, nearest first (stable for equal depths), are
    tile_gaussians[tile_offsets[t]:tile_offsets[t + 1]].

    The depth order is cut into one contiguous chunk per thread; each thread counts, then writes, its
    chunk's entries, starting in each tile after the nearer chunks' entries, so the lists come out as a
    serial pass over the depth order would write them.
    """
    tiles_x = (width + tile_size - 1) // tile_size
    n_tiles = tiles_x * ((height + tile_size - 1) // tile_size)
    rects = np.zeros((means2d.shape[0], 4), dtype=np.int64)  # tile columns [0, 1) and rows [2, 3)
    for g in prange(means2d.shape[0]):
        if not drawn[g]:
            continue
        x0 = max(math.ceil(means2d[g, 0] - extents[g, 0] - 0.5), region[2])
        x1 = min(math.floor(means2d[g, 0] + extents[g, 0] - 0.5), region[3] - 1)
        y0 = max(math.ceil(means2d[g, 1] - extents[g, 1] - 0.5), region[0])
        y1 = min(math.floor(means2d[g, 1] + extents[g, 1] - 0.5), region[1] - 1)
        if x0 > x1 or y0 > y1:
            continue
        rects[g, 0] = x0 // tile_size
        rects[g, 1] = x1 // tile_size + 1
        rects[g, 2] = y0 // tile_size
        rects[g, 3] = y1 // tile_size + 1
    order = depth_order(depth_keys, drawn, key_bits)
    n_chunks = max(1, min(n_threads, order.shape[0]))
    chunk = (order.shape[0] + n_chunks - 1) // n_chunks
    counts = np.zeros((n_chunks, n_tiles), dtype=np.int64)
    for k in prange(n_chunks):
        for i in range(k * chunk, min((k + 1) * chunk, order.shape[0])):
            g = order[i]
            for ty in range(rects[g, 2], rects[g, 3]):
                for tx in range(rects[g, 0], rects[g, 1]):
                    counts[k, ty * tiles_x + tx] += 1
    offsets = np.zeros(n_tiles + 1, dtype=np.int64)
    cursors = np.empty((n_chunks, n_tiles), dtype=np.int64)
    for t in range(n_tiles):
        position = offsets[t]
        for k in range(n_chunks):
            cursors[k, t] = position
            position += counts[k, t]
        offsets[t + 1] = position
    tile_gaussians = np.empty(offsets[-1], dtype=np.int32)
    for k in prange(n_chunks):
        for i in range(k * chunk, min((k + 1) * chunk, order.shape[0])):
            g = order[i]
            for ty in range(rects[g, 2], rects[g, 3]):
                for tx in range(rects[g, 0], rects[g, 1]):
                    t = ty * tiles_x + tx
                    tile_gaussians[cursors[k, t]] = g
                    cursors[k, t] += 1
    return offsets, tile_gaussians


@njit(cache=True, parallel=True)
def pack_intersections(means2d, conics, opacities, features, spans, tile_gaussians, n_threads):
    """(n_intersections, P_FEATURES + C) rows, row j holding Gaussian tile_gaussians[j]'s 2D mean, conic,
    opacity, span constants and features (columns P_MEAN_X ... P_FEATURES)."""
    count = tile_gaussians.shape[0]
    packed = np.empty((count, P_FEATURES + features.shape[1]), dtype=means2d.dtype)
    for chunk in prange(n_threads):
        for j in range(chunk * count // n_threads, (chunk + 1) * count // n_threads):
            g = tile_gaussians[j]
            packed[j, P_MEAN_X], packed[j, P_MEAN_Y] = means2d[g, 0], means2d[g, 1]
            packed[j, P_CONIC_A], packed[j, P_CONIC_B], packed[j, P_CONIC_C] = conics[g, 0], conics[g, 1], conics[g, 2]
            packed[j, P_OPACITY] = opacities[g]
            for k in range(4):
                packed[j, P_SPAN + k] = spans[g, k]
            for ch in range(features.shape[1]):
                packed[j, P_FEATURES + ch] = features[g, ch]
    return packed


@njit(cache=True)
def tile_schedule(tile_offsets):
    """Tile ids by decreasing number of Gaussians, to be dealt round-robin to the threads."""
    return np.argsort(-np.diff(tile_offsets), kind="mergesort")


@njit(cache=True, parallel=True, fastmath=FASTMATH)
def rasterize_forward(packed, background, tile_offsets, schedule, width, height, tile_size, n_threads, region):
    """Front-to-back compositing of the binned Gaussians.

    packed (n_intersections, P_FEATURES + C) from `pack_intersections`, background (C,); region as for
    `bin_gaussians`: pixels outside it are not composited (background, transmittance 1, no Gaussian).
    Returns image (H, W, C), transmittance (H, W) left after the last Gaussian, last (H, W) int32
    index into tile_gaussians of the last Gaussian that contributed (-1: none), and
    intersection_weights (n_intersections,) = sum over the tile's pixels of T * alpha.
    """
    dtype = packed.dtype
    half, one, alpha_max, alpha_min, transmittance_min, zero = _compositing_constants(packed)
    channels = packed.shape[1] - P_FEATURES
    rgb = channels == 3  # the common case, unrolled: about 5% off
    tiles_x = (width + tile_size - 1) // tile_size
    image = np.empty((height, width, channels), dtype=dtype)
    transmittance = np.empty((height, width), dtype=dtype)
    last = np.empty((height, width), dtype=np.int32)
    intersection_weights = np.zeros(packed.shape[0], dtype=dtype)
    for thread in prange(n_threads):
        pixels = tile_size * tile_size
        tile_T = np.empty(pixels, dtype=dtype)
        tile_color = np.empty((pixels, channels), dtype=dtype)
        tile_last = np.empty(pixels, dtype=np.int32)
        tile_done = np.empty(pixels, dtype=np.bool_)
        centre_x = np.empty(tile_size, dtype=dtype)
        centre_y = np.empty(tile_size, dtype=dtype)
        for k in range(thread, schedule.shape[0], n_threads):
            t = schedule[k]
            x0 = (t % tiles_x) * tile_size
            y0 = (t // tiles_x) * tile_size
            x1 = min(x0 + tile_size, width) - 1
            y1 = min(y0 + tile_size, height) - 1
            _pixel_centres(x0, centre_x)
            _pixel_centres(y0, centre_y)
            tile_T[:] = 1.0
            tile_color[:] = 0.0
            tile_last[:] = -1
            remaining = 0
            for y in range(y0, y1 + 1):
                for x in range(x0, x1 + 1):
                    inside = region[0] <= y < region[1] and region[2] <= x < region[3]
                    tile_done[(y - y0) * tile_size + (x - x0)] = not inside
                    remaining += inside
            for j in range(tile_offsets[t], tile_offsets[t + 1]):
                if remaining == 0:
                    break
                row = packed[j]
                mx, my = row[P_MEAN_X], row[P_MEAN_Y]
                a, b, c = row[P_CONIC_A], row[P_CONIC_B], row[P_CONIC_C]
                opacity = row[P_OPACITY]
                span = row[P_SPAN : P_SPAN + 4]
                f0, f1, f2 = (row[P_FEATURES], row[P_FEATURES + 1], row[P_FEATURES + 2]) if rgb else (zero, zero, zero)
                row_first, row_last = _row_range(my, span, y0, y1)
                weight_sum = zero
                for y in range(row_first, row_last + 1):
                    dy = my - centre_y[y - y0]
                    lo, hi = _row_span(mx, dy, b, span, x0, x1)
                    for x in range(lo, hi + 1):
                        p = (y - y0) * tile_size + (x - x0)
                        if tile_done[p]:
                            continue
                        dx = mx - centre_x[x - x0]
                        sigma = half * (a * dx * dx + c * dy * dy) + b * dx * dy
                        alpha = min(alpha_max, opacity * math.exp(-sigma))
                        if sigma < zero or alpha < alpha_min:
                            continue
                        next_T = tile_T[p] * (one - alpha)
                        if next_T <= transmittance_min:
                            tile_done[p] = True
                            remaining -= 1
                            continue
                        weight = alpha * tile_T[p]
                        if rgb:
                            tile_color[p, 0] += weight * f0
                            tile_color[p, 1] += weight * f1
                            tile_color[p, 2] += weight * f2
                        else:
                            for ch in range(channels):
                                tile_color[p, ch] += weight * row[P_FEATURES + ch]
                        weight_sum += weight
                        tile_T[p] = next_T
                        tile_last[p] = j
                intersection_weights[j] = weight_sum
            for y in range(y0, y1 + 1):
                for x in range(x0, x1 + 1):
                    p = (y - y0) * tile_size + (x - x0)
                    for ch in range(channels):
                        image[y, x, ch] = tile_color[p, ch] + tile_T[p] * background[ch]
                    transmittance[y, x] = tile_T[p]
                    last[y, x] = tile_last[p]
    return image, transmittance, last, intersection_weights


@njit(cache=True, inline="always")
def _any_gradient(grad_image, grad_alpha, x0, x1, y0, y1):
    """Whether any pixel of the tile [x0, x1] x [y0, y1] has a non-zero upstream gradient."""
    for y in range(y0, y1 + 1):
        for x in range(x0, x1 + 1):
            if grad_alpha[y, x] != 0.0:
                return True
            for ch in range(grad_image.shape[2]):
                if grad_image[y, x, ch] != 0.0:
                    return True
    return False


@njit(cache=True, parallel=True, fastmath=FASTMATH)
def rasterize_backward(
    packed, background, tile_offsets, schedule, width, height, tile_size, n_threads, transmittance, last,
    grad_image, grad_alpha,
):  # fmt: skip
    """Gradients of a loss through `rasterize_forward`, back to front, per intersection.

    grad_image (H, W, C) and grad_alpha (H, W) are dL/d(image) and dL/d(alpha = 1 - transmittance).
    Returns records (n_intersections, 6 + C) with columns G_MEAN_X, G_MEAN_Y, G_CONIC_A..C,
    G_OPACITY, then the C feature gradients.
    """
    dtype = packed.dtype
    half, one, alpha_max, alpha_min, _, zero = _compositing_constants(packed)
    channels = packed.shape[1] - P_FEATURES
    rgb = channels == 3  # unrolled, as in the forward kernel
    tiles_x = (width + tile_size - 1) // tile_size
    records = np.zeros((packed.shape[0], G_FEATURES + channels), dtype=dtype)
    for thread in prange(n_threads):
        pixels = tile_size * tile_size
        tile_T = np.empty(pixels, dtype=dtype)
        tile_behind = np.empty((pixels, channels), dtype=dtype)
        tile_last = np.empty(pixels, dtype=np.int32)
        tile_grad = np.empty((pixels, channels), dtype=dtype)  # the tile's dL/d(image)
        tile_grad_alpha = np.empty(pixels, dtype=dtype)  # dL/d(alpha) times the final transmittance
        grad_color = np.empty(channels, dtype=dtype)
        centre_x = np.empty(tile_size, dtype=dtype)
        centre_y = np.empty(tile_size, dtype=dtype)
        for k in range(thread, schedule.shape[0], n_threads):
            t = schedule[k]
            if tile_offsets[t] == tile_offsets[t + 1]:
                break  # the schedule is sorted by cost: only empty tiles remain
            x0 = (t % tiles_x) * tile_size
            y0 = (t // tiles_x) * tile_size
            x1 = min(x0 + tile_size, width) - 1
            y1 = min(y0 + tile_size, height) - 1
            if not _any_gradient(grad_image, grad_alpha, x0, x1, y0, y1):
                continue  # a masked loss: nothing flows back through this tile, its records stay zero
            _pixel_centres(x0, centre_x)
            _pixel_centres(y0, centre_y)
            tile_last[:] = -1
            max_last = -1
            for y in range(y0, y1 + 1):
                for x in range(x0, x1 + 1):
                    p = (y - y0) * tile_size + (x - x0)
                    tile_T[p] = transmittance[y, x]
                    tile_grad_alpha[p] = grad_alpha[y, x] * transmittance[y, x]
                    for ch in range(channels):
                        tile_grad[p, ch] = grad_image[y, x, ch]
                    tile_last[p] = last[y, x]
                    max_last = max(max_last, last[y, x])
                    for ch in range(channels):
                        tile_behind[p, ch] = transmittance[y, x] * background[ch]
            for j in range(max_last, tile_offsets[t] - 1, -1):
                row = packed[j]
                mx, my = row[P_MEAN_X], row[P_MEAN_Y]
                a, b, c = row[P_CONIC_A], row[P_CONIC_B], row[P_CONIC_C]
                opacity = row[P_OPACITY]
                span = row[P_SPAN : P_SPAN + 4]
                row_first, row_last = _row_range(my, span, y0, y1)
                f0, f1, f2 = (row[P_FEATURES], row[P_FEATURES + 1], row[P_FEATURES + 2]) if rgb else (zero, zero, zero)
                g_mx = zero
                g_my = zero
                g_a = zero
                g_b = zero
                g_c = zero
                g_opacity = zero
                g_f0 = zero
                g_f1 = zero
                g_f2 = zero
                grad_color[:] = 0.0
                for y in range(row_first, row_last + 1):
                    dy = my - centre_y[y - y0]
                    lo, hi = _row_span(mx, dy, b, span, x0, x1)
                    for x in range(lo, hi + 1):
                        p = (y - y0) * tile_size + (x - x0)
                        if j > tile_last[p]:
                            continue
                        dx = mx - centre_x[x - x0]
                        sigma = half * (a * dx * dx + c * dy * dy) + b * dx * dy
                        gaussian = math.exp(-sigma)
                        alpha_raw = opacity * gaussian
                        alpha = min(alpha_max, alpha_raw)
                        if sigma < zero or alpha < alpha_min:
                            continue
                        inv_one_minus_alpha = one / (one - alpha)
                        T = tile_T[p] * inv_one_minus_alpha
                        weight = alpha * T
                        grad_alpha_here = tile_grad_alpha[p] * inv_one_minus_alpha
                        if rgb:
                            u0, u1, u2 = tile_grad[p, 0], tile_grad[p, 1], tile_grad[p, 2]
                            g_f0 += weight * u0
                            g_f1 += weight * u1
                            g_f2 += weight * u2
                            grad_alpha_here += (
                                u0 * (f0 * T - tile_behind[p, 0] * inv_one_minus_alpha)
                                + u1 * (f1 * T - tile_behind[p, 1] * inv_one_minus_alpha)
                                + u2 * (f2 * T - tile_behind[p, 2] * inv_one_minus_alpha)
                            )
                            tile_behind[p, 0] += weight * f0
                            tile_behind[p, 1] += weight * f1
                            tile_behind[p, 2] += weight * f2
                        else:
                            for ch in range(channels):
                                upstream = tile_grad[p, ch]
                                grad_color[ch] += weight * upstream
                                grad_alpha_here += upstream * (
                                    row[P_FEATURES + ch] * T - tile_behind[p, ch] * inv_one_minus_alpha
                                )
                                tile_behind[p, ch] += weight * row[P_FEATURES + ch]
                        tile_T[p] = T
                        if alpha_raw <= alpha_max:
                            g_opacity += grad_alpha_here * gaussian
                            grad_sigma = -grad_alpha_here * alpha
                            g_mx += grad_sigma * (a * dx + b * dy)
                            g_my += grad_sigma * (b * dx + c * dy)
                            g_a += half * grad_sigma * dx * dx
                            g_b += grad_sigma * dx * dy
                            g_c += half * grad_sigma * dy * dy
                records[j, G_MEAN_X] = g_mx
                records[j, G_MEAN_Y] = g_my
                records[j, G_CONIC_A] = g_a
                records[j, G_CONIC_B] = g_b
                records[j, G_CONIC_C] = g_c
                records[j, G_OPACITY] = g_opacity
                if rgb:
                    records[j, G_FEATURES], records[j, G_FEATURES + 1], records[j, G_FEATURES + 2] = g_f0, g_f1, g_f2
                else:
                    for ch in range(channels):
                        records[j, G_FEATURES + ch] = grad_color[ch]
    return records


@njit(cache=True)
def sum_per_gaussian(values, tile_gaussians, n_gaussians):
    """Reduce per-intersection rows (n_intersections, D) to per-Gaussian sums (N, D)."""
    out = np.zeros((n_gaussians, values.shape[1]), dtype=values.dtype)
    for j in range(tile_gaussians.shape[0]):
        g = tile_gaussians[j]
        for d in range(values.shape[1]):
            out[g, d] += values[j, d]
    return out


@njit(cache=True, parallel=True)
def max_pixel_weights(means2d, conics, opacities, tile_offsets, tile_gaussians, region, tile_size):
    """Per intersection, the largest T * alpha the Gaussian reaches at any pixel of `region` in its tile.

    region (H, W) bool selects the pixels; the compositing follows `rasterize_forward` exactly (every
    pixel of a tile that holds region pixels is composited, so transmittances are the image's).
    Returns (n_intersections,) weights, 0 for Gaussians that reach no region pixel.
    """
    height, width = region.shape
    tiles_x = (width + tile_size - 1) // tile_size
    n_tiles = tile_offsets.shape[0] - 1
    out = np.zeros(tile_gaussians.shape[0], dtype=means2d.dtype)
    for t in prange(n_tiles):
        x0 = (t % tiles_x) * tile_size
        y0 = (t // tiles_x) * tile_size
        x1 = min(x0 + tile_size, width)
        y1 = min(y0 + tile_size, height)
        if not region[y0:y1, x0:x1].any():
            continue
        for y in range(y0, y1):
            for x in range(x0, x1):
                if not region[y, x]:
                    continue
                T = 1.0
                for j in range(tile_offsets[t], tile_offsets[t + 1]):
                    g = tile_gaussians[j]
                    dx = means2d[g, 0] - (x + 0.5)
                    dy = means2d[g, 1] - (y + 0.5)
                    sigma = 0.5 * (conics[g, 0] * dx * dx + conics[g, 2] * dy * dy) + conics[g, 1] * dx * dy
                    alpha = min(ALPHA_MAX, opacities[g] * math.exp(-sigma))
                    if sigma < 0.0 or alpha < ALPHA_MIN:
                        continue
                    next_T = T * (1.0 - alpha)
                    if next_T <= TRANSMITTANCE_MIN:
                        break
                    out[j] = max(out[j], alpha * T)
                    T = next_T
    return out
