"""The pictures a person reads: the visibility colour map, bar and least-seen shading, the labelled grids."""

from __future__ import annotations

import numpy as np
import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.body import load_body_template
from avatarperfect_cli.refinement.pictures import _colour_bar, caption_strip, labelled_grid, least_seen_shade, look_lut
from avatarperfect_cli.render import Camera, look_at


def test_the_look_colours_run_from_saturated_red_to_pale_grey_with_rising_lightness():
    lut = look_lut()
    assert lut.shape == (256, 3)
    assert lut[0, 0] > 0.5 > lut[0, 1] + lut[0, 2]  # barely seen: red
    assert (lut[-1] > 0.85).all() and float(lut[-1].max() - lut[-1].min()) < 0.05  # well seen: pale grey
    lightness = lut @ torch.tensor([0.299, 0.587, 0.114])
    assert (lightness[8:] > lightness[:-8]).all()  # lighter means more seen, everywhere


def two_gaussians_in_line() -> Avatar:
    """A wide opaque Gaussian 0 in front of (nearer +Z than) a smaller Gaussian 1, both on the pelvis."""
    rest_joints = load_body_template("anny").rest_joints
    skin_logits = torch.full((2, 24), -1e9)
    skin_logits[:, 0] = 0.0
    params = {
        "means": rest_joints[0] + torch.tensor([[0.0, 0.0, 0.1], [0.0, 0.0, 0.0]]),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2),
        "log_scales": torch.tensor([[0.05, 0.05, 0.01], [0.03, 0.03, 0.01]]).log(),
        "opacity_logits": torch.logit(torch.tensor([0.9, 0.9])),
        "sh_dc": torch.zeros(2, 1, 3),
        "sh_rest": torch.zeros(2, 0, 3),
        "skin_logits": skin_logits,
    }
    return Avatar(params, rest_joints, sh_degree=0)


def test_a_barely_seen_gaussian_behind_a_well_seen_one_still_shows():
    avatar = two_gaussians_in_line()
    centre = avatar.rest_joints[0]
    K = torch.tensor([[60.0, 0.0, 16.0], [0.0, 60.0, 16.0], [0.0, 0.0, 1.0]])
    camera = Camera(K, look_at(centre + torch.tensor([0.0, 0.0, 1.0]), centre, torch.tensor([0.0, 1.0, 0.0])), 32, 32)
    shade = torch.tensor([1.0, 0.0])  # the front one well seen, the one behind it barely
    least, _, alpha = least_seen_shade(avatar, torch.zeros(24, 3), camera, shade)
    blended, _, _ = least_seen_shade(avatar, torch.zeros(24, 3), camera, shade, power=1.0)
    assert alpha[16, 16] > 0.95
    assert blended[16, 16] > 0.85  # an ordinary alpha blend hardly shows it
    assert least[16, 16] < 0.6
    assert least[0, 0] == 1.0  # no Gaussian there: nothing barely seen


def test_colour_bar_puts_the_low_end_at_the_bottom():
    lut = look_lut()
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
