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
    offsets, tile_gaussians = kernels.bin_gaussians(means2d, extents, depths.view(np.uint64), 64, drawn, 32, 32, 16, everywhere)
    lists = [list(tile_gaussians[offsets[t] : offsets[t + 1]]) for t in range(4)]
    # Tiles (0,0) (1,0) (0,1) (1,1); Gaussian 2 straddles all four, Gaussian 1 is nearest.
    assert lists == [[2, 0], [1, 2], [2], [2]]
    top_left = np.array([0, 15, 0, 15])  # rows and columns 0..14: only tile (0,0), and Gaussian 2 reaches it
    offsets, tile_gaussians = kernels.bin_gaussians(means2d, extents, depths.view(np.uint64), 64, drawn, 32, 32, 16, top_left)
    lists = [list(tile_gaussians[offsets[t] : offsets[t + 1]]) for t in range(4)]
    assert lists == [[2, 0], [], [], []]
