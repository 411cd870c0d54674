"""How far refine took an edit toward its paint: the error inside the mask and the share of the way."""

from __future__ import annotations

import pytest
import torch

from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.refinement.edit_progress import REACHED, EditProgress, paint_error, rendered_paint_error
from avatarperfect_cli.training.trainer import TrainingView
from tests.refinement.test_additional_training import camera, on_a_line, root_avatar


def test_paint_error_counts_the_mask_only():
    image, target = torch.zeros(4, 4, 3), torch.zeros(4, 4, 3)
    target[0, 0] = 1.0  # inside the mask, off by 1 in every channel
    target[3, 3] = 1.0  # outside
    mask = torch.zeros(4, 4, dtype=torch.bool)
    mask[0, :2] = True
    assert paint_error(image, target, mask) == pytest.approx(0.5)
    assert paint_error(image, target, torch.zeros(4, 4, dtype=torch.bool)) == 0.0


def test_the_share_of_the_way_and_whether_it_was_reached():
    assert EditProgress(1, 0.4, 0.1).share == pytest.approx(0.75) and EditProgress(1, 0.4, 0.1).reached
    assert EditProgress(1, 0.4, 0.4).share == 0.0 and not EditProgress(1, 0.4, 0.4).reached
    assert EditProgress(1, 0.4, 0.6).share == pytest.approx(-0.5)  # moved away from the paint
    assert EditProgress(1, 0.0, 0.0).share == 1.0  # nothing to reach
    assert EditProgress(1, 1.0, 1.0 - REACHED).reached and not EditProgress(1, 1.0, 1.01 - REACHED).reached


def test_rendered_paint_error_renders_the_edits_own_view_over_white():
    avatar = root_avatar(on_a_line(3), torch.full((3,), 0.05))
    white = torch.ones(3)
    with torch.no_grad():
        image = render_avatar(avatar, torch.zeros(24, 3), torch.zeros(3), camera(), white).image.clamp(0, 1)
    target = torch.full_like(image, 0.25)
    mask = torch.zeros(image.shape[:2], dtype=torch.bool)
    mask[10:20, 20:40] = True
    view = TrainingView(target, mask, torch.zeros(24, 3), torch.zeros(3), camera(), mask)
    assert rendered_paint_error(avatar, view) == pytest.approx(paint_error(image, target, mask), rel=1e-6)
    assert rendered_paint_error(avatar, view) > 0.0
