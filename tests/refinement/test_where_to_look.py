"""Where to look first: the revealing poses' exposure and the per-region shares of barely seen Gaussians."""

from __future__ import annotations

import pytest
import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.body import load_body_template
from avatarperfect_cli.body.regions import REGION_INDEX, body_regions
from avatarperfect_cli.refinement.visibility import barely_seen
from avatarperfect_cli.refinement.where_to_look import barely_seen_by_region, revealing_exposure, revealing_poses


@pytest.fixture(scope="module")
def avatar() -> Avatar:
    return Avatar.from_template(load_body_template("anny"))


def test_barely_seen_by_region_counts_each_regions_share_and_puts_the_largest_first(avatar: Avatar):
    regions = body_regions(avatar.params["means"], avatar.skin_weights, avatar.rest_joints)
    visibility = torch.full((len(avatar),), 10.0, dtype=torch.float64)
    crotch = torch.nonzero(regions == REGION_INDEX["crotch"])[:, 0]
    visibility[crotch[: len(crotch) // 2]] = 0.01  # half the crotch barely seen
    visibility[regions == REGION_INDEX["armpits"]] = 0.01  # every armpit Gaussian
    assert int(barely_seen(visibility).sum()) == len(crotch) // 2 + int((regions == REGION_INDEX["armpits"]).sum())
    exposure = torch.ones(len(avatar), dtype=torch.float64)  # every Gaussian shown alike
    shares = barely_seen_by_region(avatar, visibility, exposure)
    assert [name for name, _, _ in shares[:2]] == ["armpits", "crotch"]
    assert shares[1][1] == pytest.approx((len(crotch) // 2) / len(crotch)) and shares[1][2] == len(crotch)
    assert all(share == 0.0 for _, share, _ in shares[2:])
    assert sum(count for _, _, count in shares) == len(avatar)
    # what no revealing pose shows does not count: the barely seen half of the crotch hidden, the rest shown
    exposure[crotch[: len(crotch) // 2]] = 0.0
    assert dict((name, share) for name, share, _ in barely_seen_by_region(avatar, visibility, exposure))["crotch"] == 0.0


def test_revealing_exposure_shows_the_surface_and_not_the_inside(avatar: Avatar):
    """A Gaussian moved to the middle of the chest is inside the body in every revealing pose."""
    assert set(revealing_poses()) == {"T-pose", "arms raised", "legs apart", "walking step"}
    inside = avatar.with_params({name: param.detach().clone() for name, param in avatar.params.items()})
    spine = int(torch.argmax(inside.skin_weights[:, 6]))
    inside.params["means"].data[spine] = inside.rest_joints[6]
    inside.params["log_scales"].data[spine] = torch.log(torch.tensor([0.005] * 3))
    exposure = revealing_exposure(inside, size=64, azimuths=4)
    assert exposure.shape == (len(avatar),)
    assert exposure[spine] < 1e-3 * exposure.mean()
    assert (exposure > 0).float().mean() > 0.5
