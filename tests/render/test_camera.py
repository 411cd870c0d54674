"""framing_distance: every point fits in `fill` of the image, and no point is magnified beyond the bound."""

from __future__ import annotations

import pytest
import torch

from avatarperfect_cli.render.camera import framing_distance

K = torch.tensor([[100.0, 0.0, 32.0], [0.0, 100.0, 32.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
IDENTITY = torch.eye(3, dtype=torch.float64)


def project(points: torch.Tensor, distance: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel offsets from the principal point, relative to the room on each side (1 = the image edge),
    and depths, of points (N, 3) relative to the look-at point seen from -distance along +z."""
    depth = points[:, 2] + distance
    return (K[0, 0] * points[:, :2] / depth[:, None]).abs() / 32.0, depth


def test_a_flat_body_spans_exactly_fill() -> None:
    points = torch.tensor([[0.5, 0.0, 0.0], [-0.2, 0.9, 0.0], [0.0, -0.4, 0.1]], dtype=torch.float64)
    distance = float(framing_distance(points, IDENTITY, K, 64, 64, fill=0.8))
    reach, _ = project(points, distance)
    assert float(reach.max()) == pytest.approx(0.8, rel=1e-9)


@pytest.mark.parametrize("max_magnification", [1.5, 2.0])
def test_a_part_raised_toward_the_camera_backs_it_off(max_magnification: float) -> None:
    """A foot 1 m in front of a small body: fill alone would put the camera 1.1 m from the centre (the
    foot 0.1 m from the lens); the bound keeps the foot at distance / max_magnification."""
    points = torch.tensor([[0.05, 0.3, 0.0], [0.0, -0.3, 0.0], [0.05, 0.0, -1.0]], dtype=torch.float64)
    unbounded = float(framing_distance(points, IDENTITY, K, 64, 64, fill=0.9, max_magnification=1e9))
    distance = float(framing_distance(points, IDENTITY, K, 64, 64, fill=0.9, max_magnification=max_magnification))
    reach, depth = project(points, distance)
    assert distance > 1.5 * unbounded
    assert float(depth.min()) == pytest.approx(distance / max_magnification, rel=1e-9)
    assert float(reach.max()) < 0.9


def test_a_magnification_of_one_or_less_is_refused() -> None:
    with pytest.raises(ValueError, match="max_magnification"):
        framing_distance(torch.zeros(2, 3), torch.eye(3), K, 64, 64, fill=0.9, max_magnification=1.0)
