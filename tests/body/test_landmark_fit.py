"""The landmark fit on landmarks made from a known motion: exact 2-D joints, 3-D joints distorted the way
MediaPipe's are (smaller, depths squashed), the silhouette's rows from every posed vertex; the fitted
poses, posed on the same template, must put the joints back where the motion had them."""

from __future__ import annotations

import math

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


def test_a_known_walk_is_recovered_from_its_landmarks():
    template = load_body_template("anny")
    _, motion = posed_vertices(template, motions.walk(8, 10.0, 120.0))
    body_pose, transl = torch.from_numpy(motion.body_pose), torch.from_numpy(motion.transl)
    # A camera 3 m away, a little above the hips and turned, so the world and camera frames differ.
    view = look_at(torch.tensor([0.8, 0.3, 2.9]), torch.tensor([0.0, 0.1, 0.0]), torch.tensor([0.0, 1.0, 0.0])).double()
    camera = Camera(torch.tensor([[300.0, 0.0, 128.0], [0.0, 300.0, 128.0], [0.0, 0.0, 1.0]]), view.float(), 256, 256)
    truth = joints_of(template, body_pose, transl)
    in_camera = truth @ view[:3, :3].T + view[:3, 3]
    pixels = in_camera @ camera.K.double().T
    world = (in_camera - in_camera[:, :1]) * torch.tensor([0.85, 0.85, 0.55], dtype=torch.float64)
    confidence = torch.ones(len(truth), 24, dtype=torch.float64)
    confidence[:, list(UNOBSERVED)] = 0.0
    transforms = forward_kinematics(body_pose.double(), template.rest_joints.double(), transl.double())
    vertices = skin_points(template.vertices.double(), template.weights.double(), transforms) @ view[:3, :3].T + view[:3, 3]
    rows = vertices[..., 1] * camera.K[1, 1] / vertices[..., 2] + camera.K[1, 2]
    silhouette_rows = torch.stack([rows.min(1).values, rows.max(1).values], 1)
    targets = JointTargets(pixels[..., :2] / pixels[..., 2:], confidence, world, silhouette_rows)

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
