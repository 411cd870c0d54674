"""The landmark fit on landmarks made from a known motion: exact 2-D joints, 3-D joints distorted the way
MediaPipe's are (smaller, depths squashed), the silhouette's rows from every posed vertex; the fitted
poses, posed on the same template, must put the joints back where the motion had them."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from avatarperfect_cli.body import axis_angle_to_matrix, forward_kinematics, load_body_template, skin_points
from avatarperfect_cli.body.landmark_fit import JointTargets, LandmarkFitConfig, fit_poses
from avatarperfect_cli.render import Camera, look_at
from avatarperfect_cli.sample import motions
from avatarperfect_cli.sample.generate import posed_vertices

UNOBSERVED = (3, 6, 13, 14)  # spine1, spine2, collars: no landmark


def joints_of(template, body_pose: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
    """(T, 24, 3) float64 world joints by forward kinematics."""
    rest = template.rest_joints.double()
    transforms = forward_kinematics(body_pose.double(), rest, transl.double())
    return (transforms[:, :, :3, :3] @ rest[None, :, :, None])[..., 0] + transforms[:, :, :3, 3]


@dataclass
class Walk:
    """A known walk seen by `camera`: its poses, true world joints (T, 24, 3), the joints in the camera's
    frame and in its image (T, 24, 2), and the silhouette's top and bottom rows (T, 2), all float64."""

    body_pose: torch.Tensor
    transl: torch.Tensor
    truth: torch.Tensor
    in_camera: torch.Tensor
    image: torch.Tensor
    rows: torch.Tensor


def walk_seen_by(template, frames: int, camera: Camera) -> Walk:
    _, motion = posed_vertices(template, motions.walk(frames, 10.0, 120.0))
    body_pose, transl = torch.from_numpy(motion.body_pose), torch.from_numpy(motion.transl)
    view = camera.world_to_camera.double()
    truth = joints_of(template, body_pose, transl)
    in_camera = truth @ view[:3, :3].T + view[:3, 3]
    pixels = in_camera @ camera.K.double().T
    transforms = forward_kinematics(body_pose.double(), template.rest_joints.double(), transl.double())
    vertices = skin_points(template.vertices.double(), template.weights.double(), transforms) @ view[:3, :3].T + view[:3, 3]
    rows = vertices[..., 1] * camera.K[1, 1] / vertices[..., 2] + camera.K[1, 2]
    silhouette_rows = torch.stack([rows.min(1).values, rows.max(1).values], 1)
    return Walk(body_pose, transl, truth, in_camera, pixels[..., :2] / pixels[..., 2:], silhouette_rows)


def camera_at(eye: tuple[float, float, float]) -> Camera:
    """A 256² camera at `eye`, looking at a point a little above the hips."""
    view = look_at(torch.tensor(eye), torch.tensor([0.0, 0.1, 0.0]), torch.tensor([0.0, 1.0, 0.0]))
    return Camera(torch.tensor([[300.0, 0.0, 128.0], [0.0, 300.0, 128.0], [0.0, 0.0, 1.0]]), view, 256, 256)


def test_a_known_walk_is_recovered_from_its_landmarks():
    template = load_body_template("anny")
    # A camera 3 m away, a little above the hips and turned, so the world and camera frames differ.
    camera = camera_at((0.8, 0.3, 2.9))
    walk = walk_seen_by(template, 8, camera)
    body_pose, truth, in_camera = walk.body_pose, walk.truth, walk.in_camera
    world = (in_camera - in_camera[:, :1]) * torch.tensor([0.85, 0.85, 0.55], dtype=torch.float64)
    confidence = torch.ones(len(truth), 24, dtype=torch.float64)
    confidence[:, list(UNOBSERVED)] = 0.0
    targets = JointTargets(walk.image, confidence, world, walk.rows)

    fitted_pose, fitted_transl = fit_poses(template, camera, targets, LandmarkFitConfig(steps=250))
    fitted = joints_of(template, fitted_pose, fitted_transl)
    error = (fitted - truth).norm(dim=-1)
    relative = ((fitted - fitted[:, :1]) - (truth - truth[:, :1])).norm(dim=-1)
    assert float(error.median()) < 0.03 and float(relative.median()) < 0.025, (error.median(), relative.median())
    # The root orientation comes back in the world frame: the body faces where the motion had it face.
    cosines = (facing(fitted_pose) * facing(body_pose)).sum(-1)
    assert float(cosines.min()) > math.cos(math.radians(15))


def facing(body_pose: torch.Tensor) -> torch.Tensor:
    """(T, 3) world direction of the body's front (SMPL's +Z turned by the root orientation)."""
    return axis_angle_to_matrix(body_pose[:, 0].double())[:, :, 2]


def test_rows_the_frame_cuts_off_are_left_out():
    """A silhouette row marked unknown (NaN: the mask reaches the image's edge) adds nothing: with every row
    unknown the fit is the fit without rows; with one frame's bottom row 40 pixels off, that frame's joints
    land far from the truth, and with the row marked unknown as near as with every row right."""
    template = load_body_template("anny")
    camera = camera_at((0.0, 0.3, 3.0))
    walk = walk_seen_by(template, 4, camera)
    truth, truth_rows = walk.truth, walk.rows
    confidence = torch.ones(len(truth), 24, dtype=torch.float64)
    config = LandmarkFitConfig(steps=150)

    def fitted(silhouette_rows: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        targets = JointTargets(walk.image, confidence, walk.in_camera - walk.in_camera[:, :1], silhouette_rows)
        return fit_poses(template, camera, targets, config)

    without, unknown = fitted(None), fitted(torch.full_like(truth_rows, math.nan))
    for a, b in zip(without, unknown):  # the fit's own run-to-run spread is about 1e-3
        torch.testing.assert_close(a, b, rtol=0, atol=1e-2)

    wrong, marked = truth_rows.clone(), truth_rows.clone()
    wrong[1, 1] += 40.0
    marked[1, 1] = math.nan
    errors = {
        name: float((joints_of(template, *fitted(silhouette_rows))[1] - truth[1]).norm(dim=-1).mean())
        for name, silhouette_rows in (("right", truth_rows), ("wrong", wrong), ("unknown", marked))
    }
    assert errors["unknown"] < 1.5 * errors["right"] and errors["unknown"] < errors["wrong"] / 3, errors
