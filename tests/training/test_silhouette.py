"""The silhouette distances: the nearest-point kernel against brute force, and the distances of a posed body
against its own masks and against moved masks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from avatarperfect_cli.body import forward_kinematics, load_body_template, skin_points
from avatarperfect_cli.datasets import FrameRange, VideoDataset, load_people_snapshot
from avatarperfect_cli.training.silhouette import _nearest_kernel, silhouette_loss, silhouettes

SAMPLE = Path(__file__).resolve().parents[2] / "examples" / "sample" / "train"


def test_nearest_kernel_matches_brute_force() -> None:
    rng = np.random.default_rng(1)
    points = rng.uniform(-20.0, 120.0, size=(3, 400, 2))  # some outside the 100 x 80 image
    queries = rng.uniform(0.0, 80.0, size=(3, 150, 2))
    nearest = _nearest_kernel(points, queries, 100, 80, 4.0)
    distances = np.linalg.norm(queries[:, :, None] - points[:, None], axis=-1)
    chosen = np.take_along_axis(distances, nearest[..., None], axis=2)[..., 0]
    np.testing.assert_allclose(chosen, distances.min(axis=2), rtol=0, atol=1e-12)


def test_the_true_body_is_nearer_its_masks_than_a_moved_one() -> None:
    """The sample's own body, posed by its own poses, lies on its masks (a small fraction of a pixel on
    average); moved 4 cm sideways (about 2 pixels here) it is several times farther, in every frame."""
    video = load_people_snapshot(SAMPLE, FrameRange(0, 59, 10), downscale=1)
    template = load_body_template("anny", phenotype=video.subject["phenotype"])
    data = silhouettes(video, torch.arange(len(video)), 96, 200)
    posed = skin_points(template.vertices, template.weights, forward_kinematics(video.body_pose, template.rest_joints, video.transl))
    on_masks = silhouette_loss(posed, data, huber=2.0)
    moved = silhouette_loss(posed + torch.tensor([0.04, 0.0, 0.0]), data, huber=2.0)
    assert on_masks.shape == (len(video),)
    assert float(on_masks.max()) < 0.1
    assert bool((moved > 3.0 * on_masks).all()), (on_masks, moved)
