"""The pictures a person reads: the visibility colour map and bar."""

from __future__ import annotations

import numpy as np
import torch

from avatarperfect_cli.refinement.pictures import _colour_bar, caption_strip, labelled_grid, viridis_lut


def test_viridis_runs_from_dark_purple_to_yellow_with_rising_lightness():
    lut = viridis_lut()
    assert lut.shape == (256, 3)
    torch.testing.assert_close(lut[0], torch.tensor([68, 1, 84]) / 255.0, atol=2 / 255, rtol=0)
    torch.testing.assert_close(lut[-1], torch.tensor([253, 231, 37]) / 255.0, atol=2 / 255, rtol=0)
    lightness = lut @ torch.tensor([0.299, 0.587, 0.114])
    assert (lightness[8:] > lightness[:-8]).all()  # perceptual: darker means less seen, everywhere


def test_colour_bar_puts_the_low_end_at_the_bottom():
    lut = viridis_lut()
    bar = _colour_bar(lut, 1e-4, 1e-1, 200, "label").astype(np.float32) / 255.0
    column = torch.from_numpy(bar[:, 8])
    coloured = (column - 1.0).abs().sum(1) > 0.02  # rows of the bar, not the white margin
    rows = column[coloured][1:-1]  # inside the frame lines
    assert len(rows) > 150
    assert torch.dist(rows[0], lut[-1]) < 0.03 and torch.dist(rows[-1], lut[0]) < 0.03


def test_labelled_grid_titles_the_columns_and_labels_the_rows():
    import matplotlib

    matplotlib.use("Agg")
    image = torch.rand(20, 30, 3)
    figure = labelled_grid([[image, image], [image, None]], ["round 1", "round 2"], ["suggested", "result"])
    axes = figure.axes
    assert [axis.get_title() for axis in axes] == ["suggested", "result", "", ""]
    assert [axes[0].get_ylabel(), axes[2].get_ylabel()] == ["round 1", "round 2"]
    assert [len(axis.images) for axis in axes] == [1, 1, 1, 0]  # the empty panel says "not yet"
    assert axes[3].texts[0].get_text() == "not yet"


def test_caption_strip_writes_each_label_over_its_own_panel():
    strip = caption_strip(["ground truth", "", "avatar 003"], 64)
    assert strip.shape[1] == 3 * 64 and strip.shape[0] % 2 == 0
    inked = (strip < 0.5).any(dim=2).any(dim=0)
    assert inked[:64].any() and not inked[64:128].any() and inked[128:].any()
