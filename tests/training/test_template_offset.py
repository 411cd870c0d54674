"""The template offset: the committed sample's poses with their translations moved by a known amount, and
the exact template of its subject, so the offset that puts the template back on the masks is that amount."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from avatarperfect_cli.body import load_body_template
from avatarperfect_cli.datasets import FrameRange, VideoDataset, load_people_snapshot
from avatarperfect_cli.training.template_offset import OffsetSearch, fit_transl_offset

SAMPLE = Path(__file__).resolve().parents[2] / "examples" / "sample" / "train"


@pytest.fixture(scope="module")
def video() -> VideoDataset:
    return load_people_snapshot(SAMPLE, FrameRange(0, 59, 3), downscale=2)


@pytest.fixture(scope="module")
def template(video: VideoDataset):
    return load_body_template("anny", phenotype=video.subject["phenotype"])


@pytest.mark.parametrize("moved", [(0.0, -0.4, 0.0), (0.15, 0.3, 0.0), (0.0, 0.0, 0.0)])
def test_a_known_offset_is_recovered_within_2_cm(video: VideoDataset, template, moved: tuple[float, float, float]):
    """The sample's camera looks along -Z, so every offset here lies in the image plane the fit covers."""
    shifted = VideoDataset(**{**vars(video), "transl": video.transl + torch.tensor(moved)})
    fit = fit_transl_offset(template, shifted)
    assert float((fit.offset + torch.tensor(moved)).norm()) < 0.02, fit.offset
    assert fit.iou > 0.5


def test_the_fit_leaves_the_viewing_direction_alone(video: VideoDataset, template):
    """Depth only changes the silhouette's size, which the template's own size confounds: not fitted."""
    shifted = VideoDataset(**{**vars(video), "transl": video.transl + torch.tensor([0.0, 0.2, 0.5])})
    fit = fit_transl_offset(template, shifted, OffsetSearch(frames=4, rounds=2))
    forward = video.camera.world_to_camera[2, :3]
    assert abs(float(fit.offset @ forward)) < 1e-6 and float(fit.offset.norm()) > 0.05
