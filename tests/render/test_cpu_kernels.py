"""Kernel pieces with exact answers: the depth sort and the per-tile binning."""

from __future__ import annotations

import numpy as np
import pytest

from avatarperfect_cli.render import cpu_kernels as kernels


@pytest.mark.parametrize("dtype,bits", [(np.float32, 32), (np.float64, 64)])
def test_depth_order_is_a_stable_sort_of_drawn_gaussians(dtype, bits):
    rng = np.random.default_rng(0)
    depths = rng.choice(rng.uniform(0.1, 50.0, 400), 3000).astype(dtype)  # many exact ties
    depths[:10] = -1.0  # behind the camera: never drawn
    drawn = rng.random(3000) < 0.8
    drawn[:10] = False
    keys = depths.view(np.uint32 if bits == 32 else np.uint64)
    order = kernels.depth_order(keys, drawn, bits)
    candidates = np.nonzero(drawn)[0]
    expected = candidates[np.argsort(depths[candidates], kind="stable")]
    np.testing.assert_array_equal(order, expected)


def test_binning_lists_each_touched_tile_nearest_first():
    means2d = np.array([[8.0, 8.0], [20.0, 8.0], [16.0, 16.0]])
    extents = np.array([[2.0, 2.0], [2.0, 2.0], [3.0, 3.0]])
    depths = np.array([3.0, 1.0, 2.0])
    drawn = np.ones(3, dtype=np.bool_)
    everywhere = np.array([0, 32, 0, 32])
    offsets, tile_gaussians = kernels.bin_gaussians(means2d, extents, depths.view(np.uint64), 64, drawn, 32, 32, 16, everywhere, 2)
    lists = [list(tile_gaussians[offsets[t] : offsets[t + 1]]) for t in range(4)]
    # Tiles (0,0) (1,0) (0,1) (1,1); Gaussian 2 straddles all four, Gaussian 1 is nearest.
    assert lists == [[2, 0], [1, 2], [2], [2]]
    top_left = np.array([0, 15, 0, 15])  # rows and columns 0..14: only tile (0,0), and Gaussian 2 reaches it
    offsets, tile_gaussians = kernels.bin_gaussians(means2d, extents, depths.view(np.uint64), 64, drawn, 32, 32, 16, top_left, 2)
    lists = [list(tile_gaussians[offsets[t] : offsets[t + 1]]) for t in range(4)]
    assert lists == [[2, 0], [], [], []]


@pytest.mark.parametrize("threads", [1, 2, 7])
def test_binning_matches_a_brute_force_assignment(threads):
    """Many Gaussians, ties in depth, undrawn ones and a region: every tile lists exactly the drawn Gaussians
    whose box touches it inside the region, nearest first and in index order among equal depths."""
    rng = np.random.default_rng(3)
    n, size, tile = 500, 64, 16
    means2d = rng.uniform(-8, size + 8, (n, 2))
    extents = rng.uniform(0.5, 12, (n, 2))
    depths = rng.choice(np.array([1.0, 2.0, 2.5, 4.0]), n) + rng.choice(np.array([0.0, 0.125]), n)
    drawn = rng.random(n) > 0.1
    region = np.array([5, 50, 12, 64])
    offsets, tile_gaussians = kernels.bin_gaussians(means2d, extents, depths.view(np.uint64), 64, drawn, size, size, tile, region, threads)
    tiles_x = size // tile
    for t in range(tiles_x * tiles_x):
        tx, ty = t % tiles_x, t // tiles_x
        expected = []
        for g in sorted(range(n), key=lambda g: (depths[g], g)):
            x0 = max(np.ceil(means2d[g, 0] - extents[g, 0] - 0.5), region[2])
            x1 = min(np.floor(means2d[g, 0] + extents[g, 0] - 0.5), region[3] - 1)
            y0 = max(np.ceil(means2d[g, 1] - extents[g, 1] - 0.5), region[0])
            y1 = min(np.floor(means2d[g, 1] + extents[g, 1] - 0.5), region[1] - 1)
            if drawn[g] and x0 <= x1 and y0 <= y1 and x0 // tile <= tx <= x1 // tile and y0 // tile <= ty <= y1 // tile:
                expected.append(g)
        assert list(tile_gaussians[offsets[t] : offsets[t + 1]]) == expected, t
