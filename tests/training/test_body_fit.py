"""The body fit on the committed sample whose truth is known (its exact body, its translations moved by a
known amount)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from avatarperfect_cli.body import load_body_template
from avatarperfect_cli.body.anny_model import default_cache_dir, load_anny_model
from avatarperfect_cli.datasets import FrameRange, VideoDataset, load_people_snapshot
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.training.body_fit import BodyFitConfig, fit_body, fit_picture
from avatarperfect_cli.training.silhouette import silhouettes

SAMPLE = Path(__file__).resolve().parents[2] / "examples" / "sample" / "train"
QUICK = BodyFitConfig(frames=8, resolution=96, points=1500, contour_pixels=200, starts=({},), start_steps=40, shape_steps=60)


@pytest.fixture(scope="module")
def video() -> VideoDataset:
    return load_people_snapshot(SAMPLE, FrameRange(0, 59, 3), downscale=1)


def test_the_exact_body_moved_in_the_image_plane_is_put_back(video: VideoDataset) -> None:
    """The sample's own template with its translations moved 5 cm sideways and 3 cm down: the fit of a given
    template finds the offset back and leaves the skeleton nearly alone."""
    template = load_body_template("anny", phenotype=video.subject["phenotype"])
    moved = torch.tensor([0.05, -0.03, 0.0])
    shifted = VideoDataset(**{**vars(video), "transl": video.transl + moved})
    fit = fit_body(shifted, torch.zeros(3), QUICK, template=template)
    assert float((fit.transl_offset + moved).norm()) < 0.01, fit.transl_offset
    assert float(fit.bone_offsets.norm(dim=1).mean()) < 0.01
    assert fit.loss < fit.start_loss
    assert fit.phenotype == {}


def test_anny_fit_from_the_middle_lands_near_the_true_skeleton(video: VideoDataset) -> None:
    """From anny's middle phenotype, the fitted body's rest joints come closer to the sample's than the start's."""
    truth = load_body_template("anny", phenotype=video.subject["phenotype"])
    start = load_body_template("anny")
    fit = fit_body(video, torch.zeros(3), QUICK, anny_model=load_anny_model(default_cache_dir(), progress=False))
    fitted = load_body_template("anny", phenotype=fit.phenotype).with_bone_offsets(fit.bone_offsets)
    # the root's own placement is the translation offset's business: compare joints relative to the root
    start_error = ((start.rest_joints - start.rest_joints[0]) - (truth.rest_joints - truth.rest_joints[0])).norm(dim=1).mean()
    fitted_error = ((fitted.rest_joints - fitted.rest_joints[0]) - (truth.rest_joints - truth.rest_joints[0])).norm(dim=1).mean()
    assert float(fitted_error) < 0.02
    assert float(fitted_error) < float(start_error)
    assert all(0.0 < value < 1.0 for value in fit.phenotype.values())
    picture, (iou_start, iou_fitted) = fit_picture(
        video, [(start, video.body_pose, video.transl), (fitted, video.body_pose, video.transl + fit.transl_offset)], columns=2, resolution=64
    )
    assert picture.shape[2] == 3 and picture.shape[1] == 2 * (picture.shape[0] // 2)
    assert iou_fitted > iou_start


@pytest.mark.parametrize("fill", [False, True])
def test_a_mask_with_no_body_to_fit_is_named(video: VideoDataset, fill: bool) -> None:
    masks = video.masks.clone()
    masks[2] = fill
    broken = VideoDataset(**{**vars(video), "masks": masks})
    with pytest.raises(AvatarPerfectError, match=f"frame {int(video.frame_ids[2])} is"):
        silhouettes(broken, torch.arange(len(video)), 64, 50)
