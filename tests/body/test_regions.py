"""Body regions from skinning weights and the rest skeleton, checked against the sample texture's hidden regions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatarperfect_cli.body import load_body_template
from avatarperfect_cli.body.base import BodyTemplate
from avatarperfect_cli.body.regions import BODY_REGIONS, REGION_INDEX, body_regions
from avatarperfect_cli.sample.texture import PRESETS, REGION, face_regions


@pytest.fixture(scope="module")
def template() -> BodyTemplate:
    return load_body_template("anny", phenotype=PRESETS["default"].phenotype)


def face_labels(template: BodyTemplate) -> tuple[np.ndarray, np.ndarray]:
    """Each face's region by `body_regions` at its centre, and the face areas."""
    centres = template.vertices[template.faces].mean(dim=1)
    weights = template.weights[template.faces].mean(dim=1)
    corners = template.vertices.double().numpy()[template.faces.numpy()]
    areas = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    return body_regions(centres, weights, template.rest_joints).numpy(), areas


@pytest.mark.parametrize(
    ("name", "texture_name", "iou"), [("armpits", "armpit", 0.85), ("inner arms", "inner_arm", 0.95), ("crotch", "crotch", 0.6)]
)
def test_hidden_regions_match_the_sample_textures(template: BodyTemplate, name: str, texture_name: str, iou: float):
    """The texture marks them from the mesh's normals; the rules here use no normals and still agree."""
    labels, areas = face_labels(template)
    ours, truth = labels == REGION_INDEX[name], face_regions(template) == REGION[texture_name]
    assert areas[ours & truth].sum() / areas[ours | truth].sum() > iou


def test_every_region_is_on_the_body_where_its_name_says(template: BodyTemplate):
    labels, _ = face_labels(template)
    assert set(np.unique(labels)) == set(range(len(BODY_REGIONS)))
    centres = template.vertices[template.faces].mean(dim=1).numpy()
    joints = template.rest_joints.numpy()
    height = {name: np.median(centres[labels == REGION_INDEX[name], 1]) for name in BODY_REGIONS}
    assert height["head"] > height["torso"] > height["thighs"] > height["lower legs"] > height["feet"]
    assert height["crotch"] < joints[0, 1] < height["armpits"]
    outward = {name: np.median(np.abs(centres[labels == REGION_INDEX[name], 0])) for name in BODY_REGIONS}
    assert outward["hands"] > outward["forearms"] > outward["upper arms"] > outward["armpits"] > outward["crotch"]


def test_a_point_takes_the_region_of_the_joints_that_carry_it():
    rest_joints = load_body_template("anny").rest_joints
    weights = torch.zeros(3, 24)
    weights[0, 15] = 1.0  # head
    weights[1, [7, 10]] = 0.5  # left ankle and foot
    weights[2, [3, 16]] = torch.tensor([0.7, 0.3])  # mostly spine
    points = torch.stack([rest_joints[15], rest_joints[7], rest_joints[3] + torch.tensor([0.0, 0.0, 0.1])])
    assert [BODY_REGIONS[i] for i in body_regions(points, weights, rest_joints)] == ["head", "feet", "torso"]
