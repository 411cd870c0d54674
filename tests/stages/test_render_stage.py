"""Pieces of the render stage with exact answers."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.render import Camera, look_at
from avatarperfect_cli.stages.render import orbit_cameras, parse_background, render_avatar_views


def project(camera: Camera, point: torch.Tensor) -> torch.Tensor:
    p = camera.world_to_camera[:3, :3] @ point + camera.world_to_camera[:3, 3]
    return (camera.K @ (p / p[2]))[:2]


def test_orbit_keeps_the_centre_in_place_and_turns_around_it():
    K = torch.tensor([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]])
    center = torch.tensor([0.1, 0.9, 0.2])
    start = Camera(K, look_at(torch.tensor([0.5, 1.2, 3.0]), center, torch.tensor([0.0, 1, 0])), 100, 80)
    cameras = orbit_cameras(start, center, 4)
    assert torch.allclose(cameras[0].world_to_camera, start.world_to_camera, atol=1e-6)
    up = -start.world_to_camera[1, :3]
    for camera in cameras:
        torch.testing.assert_close(project(camera, center), project(start, center), atol=1e-4, rtol=0)
        torch.testing.assert_close((camera.center - center).norm(), (start.center - center).norm())
        torch.testing.assert_close(torch.dot(camera.center - center, up), torch.dot(start.center - center, up), atol=1e-5, rtol=0)
    # A quarter turn apart: the horizontal offsets from the centre are perpendicular.
    flat = [(c.center - center) - torch.dot(c.center - center, up) * up for c in cameras[:2]]
    assert abs(float(torch.dot(flat[0], flat[1]))) < 1e-5 * float(flat[0].norm() ** 2)
    assert math.isclose(float(flat[0].norm()), float(flat[1].norm()), rel_tol=1e-5)


@pytest.mark.parametrize("text,expected", [("white", [1.0, 1, 1]), ("black", [0.0, 0, 0]), ("0.2,0.5,1", [0.2, 0.5, 1.0])])
def test_parse_background(text, expected):
    torch.testing.assert_close(parse_background(text), torch.tensor(expected))


@pytest.mark.parametrize("text", ["mauve", "1,2,3", "0.1,0.2"])
def test_parse_background_rejects(text):
    with pytest.raises(AvatarPerfectError, match="background"):
        parse_background(text)


def test_pose_render_needs_a_png(tmp_path: Path):
    with pytest.raises(AvatarPerfectError, match=r"\.png"):
        render_avatar_views(tmp_path, tmp_path / "out.jpg", pose=tmp_path / "pose.json")
