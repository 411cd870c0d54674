"""The procedural texture and its regions on the anny template."""

from __future__ import annotations

import numpy as np
import pytest

from avatarperfect_cli.body import load_body_template
from avatarperfect_cli.body.base import BodyTemplate
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.sample.texture import (
    HIDDEN_REGIONS,
    PRESETS,
    REGION,
    REGIONS,
    face_regions,
    get_preset,
    paint_texture,
)


@pytest.fixture(scope="module")
def template() -> BodyTemplate:
    return load_body_template("anny", phenotype=PRESETS["default"].phenotype)


def _face_areas(template: BodyTemplate) -> np.ndarray:
    corners = template.vertices.double().numpy()[template.faces.numpy()]
    return 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)


def test_regions_sit_where_their_names_say(template: BodyTemplate) -> None:
    regions = face_regions(template)
    assert regions.shape == (template.faces.shape[0],)
    assert set(np.unique(regions)) == set(range(len(REGIONS)))
    centre = template.vertices.double().numpy()[template.faces.numpy()].mean(axis=1)
    joints = template.rest_joints.double().numpy()
    x, y = centre[:, 0], centre[:, 1]

    inner_arm = regions == REGION["inner_arm"]
    assert (np.abs(x[inner_arm]) > np.abs(joints[16, 0])).all()  # outside the shoulders: on the arms
    assert (y[inner_arm] < joints[16, 1]).all()  # on the underside of the T-posed arms
    armpit = regions == REGION["armpit"]
    assert (np.abs(centre[armpit] - np.where(x[armpit, None] > 0, joints[16], joints[17])).max(axis=1) < 0.2).all()
    crotch = regions == REGION["crotch"]
    assert (y[crotch] < joints[0, 1]).all() and (y[crotch] > joints[4, 1]).all()
    assert (np.abs(x[crotch]) < np.abs(joints[4, 0]) + 0.05).all()
    assert (y[regions == REGION["hair"]] > joints[12, 1]).all()
    assert (y[regions == REGION["shoes"]] < joints[4, 1]).all()

    # The hidden regions are small next to the clothes but not negligible.
    area = _face_areas(template)
    hidden = np.isin(regions, [REGION[name] for name in HIDDEN_REGIONS])
    assert 0.02 < area[hidden].sum() / area.sum() < 0.15


def test_texture_is_deterministic_for_a_seed(template: BodyTemplate) -> None:
    preset = get_preset("default")
    first = paint_texture(template, preset, size=256, seed=5)
    again = paint_texture(template, preset, size=256, seed=5)
    other = paint_texture(template, preset, size=256, seed=6)
    assert first.image.shape == (256, 256, 3) and first.image.dtype == np.uint8
    np.testing.assert_array_equal(first.image, again.image)
    assert not np.array_equal(first.image, other.image)


def test_each_face_is_painted_in_its_region_colour(template: BodyTemplate) -> None:
    preset = get_preset("female")
    texture = paint_texture(template, preset, size=512, seed=0)
    regions = texture.face_regions
    uv_centre = template.uvs.double().numpy()[template.face_uvs.numpy()].mean(axis=1)
    cols = np.clip((uv_centre[:, 0] * 512).astype(int), 0, 511)
    rows = np.clip(((1.0 - uv_centre[:, 1]) * 512).astype(int), 0, 511)
    colour = texture.image[rows, cols] / 255.0
    # Hidden regions use saturated colours that no clothing colour is near.
    for name in HIDDEN_REGIONS:
        hidden = colour[regions == REGION[name]]
        distance = np.linalg.norm(hidden - np.array(preset.hidden[name]), axis=1)
        spread = np.linalg.norm(hidden - hidden.mean(axis=0), axis=1)
        assert np.mean(distance < 0.2) > 0.3 and spread.max() > 0.2  # the colour, in a pattern
    skin = colour[regions == REGION["skin"]]
    assert np.median(np.linalg.norm(skin - np.array(preset.skin), axis=1)) < 0.08
    trousers = colour[regions == REGION["trousers"]]
    assert np.median(np.linalg.norm(trousers - np.array(preset.trousers), axis=1)) < 0.08


def test_unknown_preset_lists_the_known_ones() -> None:
    with pytest.raises(AvatarPerfectError, match="default"):
        get_preset("no-such-preset")
