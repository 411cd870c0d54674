"""SyntheticSubject renders make_sample's frames from the stored poses, and refuses other datasets."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from avatarperfect_cli.datasets import load_people_snapshot
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.render.camera import Camera
from avatarperfect_cli.sample.subject import SyntheticSubject, frame_pixels
from avatarperfect_cli.sample.texture import HIDDEN_REGIONS, REGION, REGIONS

SAMPLE = Path(__file__).resolve().parents[2] / "examples" / "sample"


@pytest.fixture(scope="module")
def subject() -> SyntheticSubject:
    return SyntheticSubject.from_dataset(SAMPLE / "train")


def _stored_camera(folder: Path) -> Camera:
    """The camera exactly as make_sample wrote it (float64; the loader's Camera is float32)."""
    with np.load(folder / "cameras.npz") as data:
        K, world_to_camera = torch.from_numpy(data["intrinsic"]), torch.from_numpy(data["extrinsic"])
        return Camera(K, world_to_camera, int(data["width"]), int(data["height"]))


def test_render_reproduces_a_training_frame_exactly(subject: SyntheticSubject) -> None:
    video = load_people_snapshot(SAMPLE / "train")
    frame = 7
    render = subject.render(video.body_pose[frame], video.transl[frame], _stored_camera(SAMPLE / "train"))
    image, mask = frame_pixels(render)
    stored = np.asarray(Image.open(SAMPLE / "train" / "images" / f"image_{frame:04d}.png"))
    np.testing.assert_array_equal(image, stored)
    np.testing.assert_array_equal(mask, video.masks[frame].numpy())
    # Labels mark exactly the foreground, with the texture's regions.
    assert ((render.labels >= 0) == mask).all()
    assert set(np.unique(render.labels[mask])) <= set(range(len(REGIONS)))


def test_render_matches_every_test_frame_and_its_hidden_region_share(subject: SyntheticSubject) -> None:
    folder = SAMPLE / "test"
    video = load_people_snapshot(folder)
    camera = _stored_camera(folder)
    region_pixels = np.zeros(len(REGIONS), np.int64)
    for frame in range(len(video)):
        render = subject.render(video.body_pose[frame], video.transl[frame], camera)
        image, mask = frame_pixels(render)
        stored = np.asarray(Image.open(folder / "images" / f"image_{frame:04d}.png")).astype(np.int64)
        # Poses are stored in float32: a pixel may round to the neighbouring level, nothing more.
        difference = np.abs(image.astype(np.int64) - stored)
        assert difference.max() <= 1 and (difference > 0).any(axis=2).mean() < 5e-4
        np.testing.assert_array_equal(mask, video.masks[frame].numpy())
        region_pixels += np.bincount(render.labels[render.labels >= 0], minlength=len(REGIONS))
    # make_sample measured the hidden regions' share of the foreground from the same labels.
    recorded = video.subject["hidden_region_fraction"]
    hidden = sum(int(region_pixels[REGION[name]]) for name in HIDDEN_REGIONS)
    assert hidden / region_pixels.sum() == pytest.approx(recorded["of_foreground"], rel=1e-3)
    for name in HIDDEN_REGIONS:
        assert region_pixels[REGION[name]] / region_pixels.sum() == pytest.approx(recorded[name], rel=1e-3, abs=1e-5)


def test_render_follows_the_translation(subject: SyntheticSubject) -> None:
    video = load_people_snapshot(SAMPLE / "test")
    camera = video.camera
    still = subject.render(video.body_pose[0], video.transl[0], camera)
    shifted = subject.render(video.body_pose[0], video.transl[0] + torch.tensor([0.1, 0.0, 0.0]), camera)
    # The camera looks down -Z with world +X to the image's right: 0.1 m moves the body f * 0.1 / depth px right.
    columns = np.arange(camera.width)
    centre, moved = ((render.coverage * columns).sum() / render.coverage.sum() for render in (still, shifted))
    pelvis = subject.template.rest_joints[0].double() + video.transl[0].double()
    depth = float(camera.world_to_camera[2, :3].double() @ pelvis + camera.world_to_camera[2, 3])
    assert moved - centre == pytest.approx(0.1 * float(camera.K[0, 0]) / depth, rel=0.1)
    background = still.coverage == 0
    np.testing.assert_array_equal(still.rgb[background], 1.0)


def test_posed_like_another_skeleton_puts_the_subject_where_that_skeleton_stands(subject: SyntheticSubject) -> None:
    video = load_people_snapshot(SAMPLE / "test")
    camera, body_pose, transl = video.camera, video.body_pose[3], video.transl[3]
    rest_joints = subject.template.rest_joints
    # Its own skeleton: the subject as it is.
    own = subject.render_posed_like(body_pose, transl, rest_joints, camera)
    np.testing.assert_allclose(own.rgb, subject.render(body_pose, transl, camera).rgb, atol=1e-6)
    # A skeleton standing 4 cm further right: the subject there.
    shift = torch.tensor([0.04, 0.0, 0.0])
    moved = subject.render_posed_like(body_pose, transl, rest_joints + shift, camera)
    expected = subject.render(body_pose, transl + shift, camera)
    assert np.abs(moved.coverage - expected.coverage).max() < 1e-3
    assert np.abs(moved.coverage - own.coverage).sum() > 100


def test_unseen_faces_are_what_no_frame_shows(subject: SyntheticSubject) -> None:
    video = load_people_snapshot(SAMPLE / "train")
    camera = video.camera
    unseen = subject.unseen_faces(video.body_pose[:1], video.transl[:1], camera)
    front = subject.face_ids(video.body_pose[0], video.transl[0], camera)
    assert ((front >= 0) == (subject.render(video.body_pose[0], video.transl[0], camera).labels >= 0)).all()
    assert not unseen[front[front >= 0]].any()  # the frame itself shows only seen faces
    # From behind (the camera turned 180 degrees about the vertical through the body), one front frame
    # saw almost none of what shows.
    pelvis = subject.template.rest_joints[0].double() + video.transl[0].double()
    turn = torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=torch.float64))
    behind = torch.eye(4, dtype=torch.float64)
    behind[:3, :3] = camera.world_to_camera[:3, :3].double() @ turn
    behind[:3, 3] = camera.world_to_camera[:3, 3].double() + camera.world_to_camera[:3, :3].double() @ (pelvis - turn @ pelvis)
    back = subject.face_ids(video.body_pose[0], video.transl[0], Camera(camera.K, behind.float(), camera.width, camera.height))
    assert (back >= 0).sum() > 0.5 * (front >= 0).sum()
    assert unseen[back[back >= 0]].mean() > 0.8
    # Every frame of the video leaves less unseen than its first frame alone.
    assert subject.unseen_faces(video.body_pose, video.transl, camera).sum() < unseen.sum()


def _copy_with_subject(tmp_path: Path, edit: dict | None) -> Path:
    folder = tmp_path / "dataset"
    folder.mkdir()
    shutil.copy(SAMPLE / "train" / "cameras.npz", folder / "cameras.npz")
    if edit is not None:
        subject = json.loads((SAMPLE / "train" / "subject.json").read_text())
        (folder / "subject.json").write_text(json.dumps({**subject, **edit}))
    return folder


@pytest.mark.parametrize(
    "edit",
    [None, {"body_model": "smpl"}, {"preset": "nobody"}, {"seed": "zero"}, {"seed": True},
     {"phenotype": {"age": 1.5}}, {"phenotype": {"stature": 0.5}}, {"phenotype": "tall"}],
)  # fmt: skip
def test_from_dataset_refuses_other_datasets_in_one_line(tmp_path: Path, edit: dict | None) -> None:
    folder = _copy_with_subject(tmp_path, edit)
    with pytest.raises(AvatarPerfectError) as caught:
        SyntheticSubject.from_dataset(folder)
    message = str(caught.value)
    assert message.startswith(f"{folder}: not a synthetic subject made by 'avatarperfect make-sample'")
    assert "\n" not in message
