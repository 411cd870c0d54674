"""What train-initial decides from a dataset's subject.json: whether to fit the body and refine the poses."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.stages.train_initial import BodySettings, InitialFit

SAMPLE = {"body_model": "anny", "phenotype": {"gender": 0.3}}  # a synthetic sample: its exact body and poses
PREPARED = {**SAMPLE, "estimated": ["body", "poses"]}  # prepare's folders: an assumed body, estimated poses


def _video(subject: dict | None) -> SimpleNamespace:
    return SimpleNamespace(subject=subject)


@pytest.mark.parametrize(
    ("shape", "subject", "fits"),
    [("auto", SAMPLE, False), ("auto", PREPARED, True), ("auto", None, True), ("fit", SAMPLE, True), ("exact", PREPARED, False)],
)
def test_the_body_is_fitted_unless_the_dataset_names_it_exactly(shape: str, subject: dict | None, fits: bool) -> None:
    assert BodySettings(shape=shape).fits_shape(_video(subject)) is fits


def test_an_unknown_body_shape_is_refused() -> None:
    with pytest.raises(AvatarPerfectError, match="unknown body shape"):
        BodySettings(shape="guess").fits_shape(_video(SAMPLE))


@pytest.mark.parametrize(
    ("refine_poses", "subject", "refines"),
    [(None, SAMPLE, False), (None, PREPARED, True), (None, None, False), (True, SAMPLE, True), (False, PREPARED, False)],
)
def test_poses_are_refined_when_asked_or_estimated(refine_poses: bool | None, subject: dict | None, refines: bool) -> None:
    assert InitialFit(refine_poses=refine_poses).refines_poses(_video(subject)) is refines
