"""Additional training (§6.3) on small synthetic avatars, without a workspace: the background tool, the split of
barely seen Gaussians under edits, the pull toward the template's skinning, the edit draws and the rates."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.body import SMPL_PARENTS, BodyTemplate
from avatarperfect_cli.body.template_skinning import template_skin_weights
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.io.pose_json import PoseFile
from avatarperfect_cli.refinement.additional_training import (
    EDIT_LOSS_WEIGHT,
    MAX_EDIT_STEP_SHARE,
    REFINE_MEANS_RATE,
    REFINE_SHAPE_RATE_FACTOR,
    STRONG_COLOUR_RATE,
    STRONG_DRAWS,
    STRONG_LOSS_WEIGHT,
    RefineSettings,
    barely_seen_rate_scales,
    delete_background,
    edit_draw_weights,
    edit_step_share,
    pull_toward_template_skinning,
    refine_config,
    seen_by_the_video,
    split_barely_seen_under_edits,
    strong_edit_rate_scales,
    strong_edit_training,
)
from avatarperfect_cli.render import Camera, look_at
from avatarperfect_cli.training.trainer import TrainConfig, TrainingView

WIDTH, HEIGHT = 64, 32
FOCAL = 50.0
EYE = torch.tensor([0.0, 0.0, 2.0])


def camera() -> Camera:
    """2 m in front of the origin on +z, looking at it, +y up."""
    K = torch.tensor([[FOCAL, 0.0, WIDTH / 2], [0.0, FOCAL, HEIGHT / 2], [0.0, 0.0, 1.0]])
    return Camera(K, look_at(EYE, torch.zeros(3), torch.tensor([0.0, 1.0, 0.0])), WIDTH, HEIGHT)


def rest_pose() -> PoseFile:
    return PoseFile(torch.zeros(24, 3), torch.zeros(3), camera())


def column_of(point: torch.Tensor) -> int:
    """The pixel column of a world point seen by `camera()`, by the pinhole model in float64."""
    view = camera().world_to_camera.double()
    local = view[:3, :3] @ point.double() + view[:3, 3]
    return math.floor(FOCAL * float(local[0] / local[2]) + WIDTH / 2)


def root_avatar(means: torch.Tensor, stds: torch.Tensor, rest_joints: torch.Tensor | None = None) -> Avatar:
    """Opaque round Gaussians at `means` (N, 3) with standard deviations `stds` (N,) metres, all skinned to the
    root, rest joints at the origin unless given: in the zero pose every Gaussian stays where it is."""
    count = len(means)
    skin_logits = torch.full((count, 24), -30.0)
    skin_logits[:, 0] = 0.0
    params = {
        "means": means.float(),
        "quats": torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(count, 1),
        "log_scales": stds.float().log()[:, None].repeat(1, 3),
        "opacity_logits": torch.full((count,), 4.0),
        "sh_dc": torch.zeros(count, 1, 3),
        "sh_rest": torch.zeros(count, 0, 3),
        "skin_logits": skin_logits,
    }
    return Avatar(params, torch.zeros(24, 3) if rest_joints is None else rest_joints, sh_degree=0)


def on_a_line(count: int, spacing: float = 0.3) -> torch.Tensor:
    """(count, 3) points along x near the origin, `spacing` metres apart (7.5 px at 2 m), their centres projecting
    into the middle of pixels (no pixel border to round across)."""
    x = (torch.arange(count) - (count - 1) / 2) * spacing + 0.5 * 2.0 / FOCAL
    return torch.stack([x, torch.zeros(count), torch.zeros(count)], dim=1)


# ------------------------------------------------------------------------ the background tool


def test_seen_by_the_video_is_at_least_the_mean_visibility():
    visibility = torch.tensor([1.0, 2.0, 3.0, 6.0], dtype=torch.float64)  # mean 3
    assert seen_by_the_video(visibility).tolist() == [False, False, True, True]


def test_background_regions_delete_the_centres_they_cover_except_the_protected():
    means = on_a_line(5)
    avatar = root_avatar(means, torch.full((5,), 0.01))
    first, second = torch.zeros(HEIGHT, WIDTH, dtype=torch.bool), torch.zeros(HEIGHT, WIDTH, dtype=torch.bool)
    for index in (0, 1):
        first[:, column_of(means[index])] = True
    second[:, column_of(means[3])] = True
    protected = torch.tensor([False, True, False, False, False])
    kept, deleted = delete_background(avatar, [(rest_pose(), first), (rest_pose(), second)], protected)
    assert deleted.tolist() == [True, False, False, True, False]
    torch.testing.assert_close(kept.params["means"], avatar.params["means"][[1, 2, 4]], rtol=0, atol=0)
    unchanged, none = delete_background(avatar, [], None)
    assert len(unchanged) == 5 and not none.any()


# ------------------------------------------------------------------------ splitting under an edit's strokes


def test_only_large_barely_seen_gaussians_under_the_strokes_are_split():
    """0: seen, behind 1; 1: barely seen, 2 cm, under the strokes (split); 2: barely seen, beside 1, but 2 mm wide;
    3: behind the camera; 4: barely seen and large, but 7.5 px away from the strokes."""
    means = on_a_line(5)
    means[0], means[2] = means[1] + torch.tensor([0.0, 0.0, -0.05]), means[1] + torch.tensor([0.0, 0.01, 0.0])
    means[3] = EYE + torch.tensor([0.0, 0.0, 1.0])
    avatar = root_avatar(means, torch.tensor([0.02, 0.02, 0.002, 0.02, 0.02]))
    seen = torch.tensor([True, False, False, False, False])
    strokes = torch.zeros(HEIGHT, WIDTH, dtype=torch.bool)
    centre = column_of(means[1])
    strokes[:, centre - 3 : centre + 4] = True
    pose = rest_pose()
    view = TrainingView(torch.ones(HEIGHT, WIDTH, 3), strokes, pose.body_pose, pose.transl, pose.camera, strokes)
    split_avatar, split_seen, count = split_barely_seen_under_edits(avatar, seen, [view], 0.1, seed=0)
    assert count == 1 and split_seen.tolist() == [True, False, False, False, False, False]
    params = {name: param.detach() for name, param in split_avatar.params.items()}
    old = {name: param.detach() for name, param in avatar.params.items()}
    for name in old:
        torch.testing.assert_close(params[name][:4], old[name][[0, 2, 3, 4]], rtol=0, atol=0)
    torch.testing.assert_close(params["log_scales"][4:], old["log_scales"][[1, 1]] - math.log(1.6))
    offsets = (params["means"][4:] - old["means"][1]).norm(dim=1)
    assert 0.0 < float(offsets.min()) and float(offsets.max()) < 5 * 0.02 * math.sqrt(3)  # samples of the parent
    _, _, none = split_barely_seen_under_edits(avatar, seen, [view], 1e6, seed=0)
    assert none == 0


# ------------------------------------------------------------------------ the pull toward the template's skinning


def smooth_template(seed: int = 0) -> BodyTemplate:
    """2000 vertices in a body-sized box, a random skeleton inside it, and weights that fall off smoothly with the
    distance to each joint (so the template's weights change slowly with position, as a body's do)."""
    generator = torch.Generator().manual_seed(seed)
    vertices = (torch.rand(2000, 3, generator=generator, dtype=torch.float64) - 0.5) * torch.tensor([0.6, 1.6, 0.3])
    joints = torch.zeros(24, 3, dtype=torch.float64)
    for joint, parent in enumerate(SMPL_PARENTS[1:], start=1):
        joints[joint] = (joints[parent] + 0.12 * torch.randn(3, generator=generator, dtype=torch.float64)).clamp(-0.4, 0.4)
    weights = torch.softmax(-torch.cdist(vertices, joints).square() / 0.02, dim=1)
    return BodyTemplate(vertices, torch.zeros(0, 3, dtype=torch.int64), weights, joints.float())


def mis_skinned_avatar(template: BodyTemplate, seed: int = 1) -> Avatar:
    """300 Gaussians near the template's vertices, skinned half as the template there and half to the parent of
    its main joint (wrong weights, as a fit that let a limb's points follow the torso)."""
    generator = torch.Generator().manual_seed(seed)
    means = template.vertices[:300] + 0.01 * torch.randn(300, 3, generator=generator, dtype=torch.float64)
    avatar = root_avatar(means, torch.full((300,), 0.01), template.rest_joints)
    weights = template_skin_weights(template, means)
    parents = torch.tensor([max(parent, 0) for parent in SMPL_PARENTS])[weights.argmax(1)]
    avatar.set_skin_weights(0.5 * weights + 0.5 * torch.nn.functional.one_hot(parents, 24).float())
    with torch.no_grad():
        avatar.params["quats"].copy_(torch.nn.functional.normalize(torch.randn(300, 4, generator=generator), dim=1))
    return avatar


def turning_frames(frames: int, seed: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """One bent pose (joints turned by ~0.15 rad) seen turning about y and moving: the frames differ by a
    rigid motion of the whole body, so re-anchoring can keep every Gaussian in place."""
    generator = torch.Generator().manual_seed(seed)
    body_pose = (0.15 * torch.randn(24, 3, generator=generator)).repeat(frames, 1, 1)
    body_pose[:, 0] = torch.stack([torch.tensor([0.0, 0.7 * k, 0.0]) for k in range(frames)])
    transl = 0.1 * torch.randn(frames, 3, generator=generator)
    return body_pose, transl


def posed(avatar: Avatar, body_pose: torch.Tensor, transl: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
    with torch.no_grad():
        return [avatar.pose(pose, offset) for pose, offset in zip(body_pose, transl)]


def test_reanchoring_gives_the_template_weights_and_keeps_every_frame_in_place():
    template = smooth_template()
    avatar = mis_skinned_avatar(template)
    body_pose, transl = turning_frames(5)
    before, means, learned = posed(avatar, body_pose, transl), avatar.params["means"].detach().clone(), avatar.skin_weights.detach()
    pull_toward_template_skinning(avatar, template, body_pose, transl, share=1.0, max_shift=0.003)
    for (old_means, old_quats), (new_means, new_quats) in zip(before, posed(avatar, body_pose, transl)):
        assert float((new_means - old_means).norm(dim=1).max()) < 1e-4
        assert float(torch.nn.functional.cosine_similarity(new_quats, old_quats, dim=1).abs().min()) > 1 - 1e-5
    assert float((avatar.params["means"].detach() - means).norm(dim=1).median()) > 0.005  # they did move
    learned_distance = (learned - template_skin_weights(template, means)).abs().sum(1)
    distance = (avatar.skin_weights.detach() - template_skin_weights(template, avatar.params["means"])).abs().sum(1)
    assert float(distance.quantile(0.9)) < 0.1 < float(learned_distance.quantile(0.1))


@pytest.mark.parametrize("share", [0.5, 1.0])
def test_without_reanchoring_an_unbounded_pull_blends_toward_the_template_at_the_means(share: float):
    template = smooth_template()
    avatar = mis_skinned_avatar(template)
    body_pose, transl = turning_frames(3)
    means, quats = avatar.params["means"].detach().clone(), avatar.params["quats"].detach().clone()
    learned = avatar.skin_weights.detach()
    pull_toward_template_skinning(avatar, template, body_pose, transl, share=share, max_shift=math.inf, reanchor=False)
    expected = (1 - share) * learned + share * template_skin_weights(template, means)
    # the skinning logits floor each weight at 1e-6 (set_skin_weights), so rows differ by up to 24e-6
    torch.testing.assert_close(avatar.skin_weights.detach(), expected, atol=3e-5, rtol=0)
    assert torch.equal(avatar.params["means"].detach(), means) and torch.equal(avatar.params["quats"].detach(), quats)


def test_a_bounded_pull_shifts_no_gaussian_further_than_the_bound_in_any_frame():
    """Frames that bend the elbows and wrists (joints 18 to 21) differently: a full pull would move the
    Gaussians skinned near them by centimetres; bounded, none moves further than 3 mm in any frame, and the ones
    whose joints stay put go the whole way."""
    template = smooth_template()
    avatar = mis_skinned_avatar(template)
    generator = torch.Generator().manual_seed(3)
    body_pose, transl = torch.zeros(4, 24, 3), torch.zeros(4, 3)
    body_pose[:, 18:22] = 0.5 * torch.randn(4, 4, 3, generator=generator)
    before, learned = posed(avatar, body_pose, transl), avatar.skin_weights.detach().clone()
    pull_toward_template_skinning(avatar, template, body_pose, transl, share=1.0, max_shift=0.003, reanchor=False)
    shifts = torch.stack([(new - old).norm(dim=1) for (old, _), (new, _) in zip(before, posed(avatar, body_pose, transl))])
    assert float(shifts.max()) < 0.003 + 5e-5  # give or take what the logits' 1e-6 floor on every joint moves
    target = template_skin_weights(template, avatar.params["means"])
    whole_way = (avatar.skin_weights.detach() - target).abs().sum(1) < 1e-3
    partly = (avatar.skin_weights.detach() - learned).abs().sum(1) > 1e-3
    assert 0 < int(whole_way.sum()) < 300 and int((partly & ~whole_way).sum()) > 0


# ------------------------------------------------------------------------ edit draws and training rates


def test_new_edits_share_the_given_part_of_the_edit_draws():
    edits = [1, 2, 3, 4]
    weights = edit_draw_weights(edits, {4}, 0.5)
    assert weights[3] == pytest.approx(sum(weights[:3])) and len(set(weights[:3])) == 1
    assert edit_draw_weights(edits, {3, 4}, 0.8) == pytest.approx([0.1, 0.1, 0.4, 0.4])
    assert edit_draw_weights(edits, {4}, None) == [1.0] * 4  # the paper: every edit alike
    assert edit_draw_weights(edits, set(), 0.5) == [1.0] * 4 == edit_draw_weights(edits, {1, 2, 3, 4}, 0.5)


def test_the_first_refine_gives_its_new_edits_the_share_later_refines_give_them():
    assert edit_step_share(0.3, 0.5, 1, 0) == pytest.approx(0.15) == edit_step_share(0.3, 0.5, 2, 0)
    assert edit_step_share(0.3, 0.5, 1, 3) == 0.3 == edit_step_share(0.3, 0.5, 0, 4)  # later refines, a refine with no new edit
    assert edit_step_share(0.3, None, 1, 0) == 0.3  # every edit alike (the paper): the full share
    assert edit_step_share(0.6, 0.8, 1, 0) == pytest.approx(0.48)


def test_refine_config_continues_the_fit_gently():
    """Positions from REFINE_MEANS_RATE, scales and rotations at REFINE_SHAPE_RATE_FACTOR of GART's rates,
    skinning from step 0, no densification; colours and opacities at GART's rates."""
    gart, config = TrainConfig().learning_rates, refine_config(RefineSettings(iterations=300))
    rates = config.learning_rates
    assert 0.0 < REFINE_SHAPE_RATE_FACTOR < 1.0
    for name in ("quats", "log_scales"):
        assert rates.at(name, 0) == pytest.approx(REFINE_SHAPE_RATE_FACTOR * gart.at(name, 0))
    for name in ("opacity_logits", "sh_dc", "sh_rest"):
        assert rates.at(name, 150) == gart.at(name, 150)
    assert rates.at("means", 0) == pytest.approx(REFINE_MEANS_RATE) and rates.at("means", 300) == pytest.approx(gart.means_final)
    assert rates.at("skin_logits", 0) == pytest.approx(gart.skin_logits) and gart.skin_logits > 0.0
    assert config.iterations == 300 and config.densify.refine_stop == 0
    assert config.edit_loss_weight == EDIT_LOSS_WEIGHT and 0.0 < EDIT_LOSS_WEIGHT < 1.0
    assert refine_config(RefineSettings(keep_shapes=True)).edit_frozen == ("quats", "log_scales")


def test_barely_seen_gaussians_get_the_first_fits_rates_and_the_others_refines():
    seen = torch.tensor([True, False, True, False])
    scales = barely_seen_rate_scales(seen)
    gart, refine_rates = TrainConfig().learning_rates, refine_config(RefineSettings()).learning_rates
    assert set(scales) == {"means", "quats", "log_scales"}
    for name, scale in scales.items():
        assert scale[seen].tolist() == [1.0, 1.0]
        torch.testing.assert_close(scale[~seen] * refine_rates.at(name, 0), torch.full((2,), gart.at(name, 0)))


def test_a_strong_edit_is_drawn_more_and_weighs_more_and_the_others_keep_their_draws():
    view = TrainingView(torch.zeros(4, 4, 3), torch.ones(4, 4, dtype=torch.bool), torch.zeros(24, 3), torch.zeros(3), camera())
    views = [replace(view, draw_weight=0.25), replace(view, draw_weight=0.75)]
    trained, share = strong_edit_training(views, [False, True], 0.2, EDIT_LOSS_WEIGHT)
    assert [v.draw_weight for v in trained] == [0.25, 0.75 * STRONG_DRAWS]
    assert trained[0].loss_weight == 1.0 and EDIT_LOSS_WEIGHT * trained[1].loss_weight == pytest.approx(STRONG_LOSS_WEIGHT)
    # the default edit is drawn in as many steps as before: 0.2 * 0.25 of them
    assert share * 0.25 / sum(v.draw_weight for v in trained) == pytest.approx(0.2 * 0.25)
    assert strong_edit_training(views, [False, False], 0.2, EDIT_LOSS_WEIGHT) == (views, 0.2)
    assert strong_edit_training(views, [True, True], 0.5, EDIT_LOSS_WEIGHT)[1] == MAX_EDIT_STEP_SHARE


def test_the_gaussians_a_strong_edit_shows_move_like_the_barely_seen_and_recolour_faster():
    seen = torch.tensor([True, True, False, False])
    shown = torch.tensor([True, False, True, False])
    scales = strong_edit_rate_scales(shown, barely_seen_rate_scales(seen))
    for name in ("means", "quats", "log_scales"):
        gart = float(barely_seen_rate_scales(torch.tensor([False]))[name][0])  # GART's rate over refine's
        assert gart > 1.0
        # shown or barely seen: GART's rates; seen and not shown: refine's
        assert scales[name].tolist() == pytest.approx([gart, 1.0, gart, gart])
        assert strong_edit_rate_scales(shown, None)[name].tolist() == pytest.approx([gart, 1.0, gart, 1.0])
    assert scales["sh_dc"].tolist() == scales["sh_rest"].tolist() == [STRONG_COLOUR_RATE, 1.0, STRONG_COLOUR_RATE, 1.0]


@pytest.mark.parametrize(
    "field,value,option",
    [("iterations", 0, "--iterations"), ("edit_probability", 1.5, "--edit-probability"), ("edit_loss_weight", 0.0, "--edit-loss-weight"),
     ("new_edit_share", 0.0, "--new-edit-share"), ("split_painted", -1.0, "split threshold"), ("template_skinning", -0.1, "--template-skinning"),
     ("template_shift", 0.0, "--template-shift-mm")],  # fmt: skip
)
def test_settings_out_of_range_are_refused_naming_the_option(field: str, value: float, option: str):
    RefineSettings().check()
    with pytest.raises(AvatarPerfectError, match=option):
        RefineSettings(**{field: value}).check()
