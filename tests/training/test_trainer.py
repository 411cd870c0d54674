"""The training loop on a tiny sphere avatar: it fits, it is deterministic, edits act only in their mask."""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.body import BodyTemplate
from avatarperfect_cli.gaussians import rgb_to_sh
from avatarperfect_cli.render import Camera, look_at
from avatarperfect_cli.training.losses import boundary_band, subject_bbox
from avatarperfect_cli.training.metrics import psnr
from avatarperfect_cli.training.progress import TrainingProgress
from avatarperfect_cli.training.strategy import DensifyConfig
from avatarperfect_cli.training.trainer import TrainConfig, TrainingView, background_alpha, train

SIZE = 48
# The sphere's Gaussians (3 cm) start above the default scale bound, which would clamp them all at the first
# step: the tests of what edits leave unchanged train without it.
UNBOUNDED = DensifyConfig(max_scale=0.0)


def sphere_template(rings: int = 16, segments: int = 24, radius: float = 0.3) -> BodyTemplate:
    """A UV sphere skinned entirely to the pelvis."""
    vertices = [[0.0, radius, 0.0]]
    for i in range(1, rings):
        theta = math.pi * i / rings
        for j in range(segments):
            phi = 2 * math.pi * j / segments
            vertices.append([radius * math.sin(theta) * math.sin(phi), radius * math.cos(theta), radius * math.sin(theta) * math.cos(phi)])
    vertices.append([0.0, -radius, 0.0])
    faces = []
    last = len(vertices) - 1
    for j in range(segments):
        faces.append([0, 1 + j, 1 + (j + 1) % segments])
        base = 1 + (rings - 2) * segments
        faces.append([last, base + (j + 1) % segments, base + j])
    for i in range(rings - 2):
        for j in range(segments):
            a, b = 1 + i * segments + j, 1 + i * segments + (j + 1) % segments
            faces += [[a, a + segments, b], [b, a + segments, b + segments]]
    weights = torch.zeros(len(vertices), 24)
    weights[:, 0] = 1
    return BodyTemplate(torch.tensor(vertices), torch.tensor(faces), weights, torch.zeros(24, 3))


def camera() -> Camera:
    K = torch.tensor([[80.0, 0, SIZE / 2], [0, 80.0, SIZE / 2], [0, 0, 1]])
    return Camera(K, look_at(torch.tensor([0.0, 0, 2.0]), torch.zeros(3), torch.tensor([0.0, 1, 0])), SIZE, SIZE)


def yaw(angle: float) -> torch.Tensor:
    pose = torch.zeros(24, 3)
    pose[0, 1] = angle
    return pose


def video_of(avatar: Avatar, frames: int = 4) -> list[TrainingView]:
    views = []
    with torch.no_grad():
        for k in range(frames):
            pose = yaw(2 * math.pi * k / frames)
            out = render_avatar(avatar, pose, torch.zeros(3), camera(), torch.ones(3))
            views.append(TrainingView(out.image, out.alpha > 0.5, pose, torch.zeros(3), camera()))
    return views


def coloured_avatar() -> Avatar:
    avatar = Avatar.from_template(sphere_template(), sh_degree=1)
    positions = avatar.params["means"].detach()
    colours = 0.5 + 0.45 * torch.sin(positions * torch.tensor([20.0, 15.0, 10.0]))
    avatar.params["sh_dc"].data = rgb_to_sh(colours)[:, None, :]
    return avatar


def mean_psnr(avatar: Avatar, views: list[TrainingView]) -> float:
    with torch.no_grad():
        return sum(
            psnr(render_avatar(avatar, v.body_pose, v.transl, v.camera, torch.ones(3)).image, v.image) for v in views
        ) / len(views)


def test_training_fits_the_video():
    views = video_of(coloured_avatar())
    avatar = Avatar.from_template(sphere_template(), sh_degree=1)
    before = mean_psnr(avatar, views)
    config = TrainConfig(iterations=150)
    config.learning_rates.sh_dc = 0.05
    train(avatar, views, config=config, progress=False)
    after = mean_psnr(avatar, views)
    assert after > before + 6, (before, after)


def test_same_seed_same_avatar():
    views = video_of(coloured_avatar())
    config = TrainConfig(iterations=25, densify=DensifyConfig(refine_start=5, refine_every=10, grad_threshold=1e-6))
    first = train(Avatar.from_template(sphere_template()), views, config=config, progress=False)
    second = train(Avatar.from_template(sphere_template()), views, config=config, progress=False)
    assert len(first) > len(sphere_template().vertices), "densification should have run"
    for name, value in first.params.items():
        assert torch.equal(value, second.params[name]), name


def test_edits_change_only_the_masked_region():
    avatar = coloured_avatar()
    video = video_of(avatar)
    with torch.no_grad():
        before = render_avatar(avatar, yaw(0.0), torch.zeros(3), camera(), torch.ones(3))
    initial = {name: value.detach().clone() for name, value in avatar.params.items()}
    mask = torch.zeros(SIZE, SIZE, dtype=torch.bool)
    mask[:, : SIZE // 2] = True
    red = torch.tensor([1.0, 0.0, 0.0]).expand(SIZE, SIZE, 3)
    edit = TrainingView(red, video[0].foreground, yaw(0.0), torch.zeros(3), camera(), loss_mask=mask)
    config = TrainConfig(iterations=60, edit_probability=1.0, densify=UNBOUNDED)
    config.learning_rates.sh_dc = 0.05
    train(avatar, video, [edit], config=config, progress=False)
    with torch.no_grad():
        after = render_avatar(avatar, yaw(0.0), torch.zeros(3), camera(), torch.ones(3)).image
    inside = video[0].foreground & mask
    red_error = lambda image, region: (image[region] - torch.tensor([1.0, 0, 0])).abs().mean()  # noqa: E731
    assert red_error(after, inside) < 0.5 * red_error(before.image, inside)
    # Gaussians whose footprint lies wholly right of the mask get exactly zero gradient: unchanged.
    untouched = (before.means2d[:, 0] - before.radii > SIZE // 2 + 1) | (before.radii == 0)
    assert untouched.sum() > 20
    for name, value in avatar.params.items():
        assert torch.equal(value[untouched], initial[name][untouched]), name


def left_half_edit(video: list[TrainingView], colour: list[float], draw_weight: float = 1.0) -> TrainingView:
    """An edit of the first frame's view painting its left half one flat colour."""
    left = torch.zeros(SIZE, SIZE, dtype=torch.bool)
    left[:, : SIZE // 2] = True
    image = torch.tensor(colour).expand(SIZE, SIZE, 3)
    return TrainingView(image, video[0].foreground, yaw(0.0), torch.zeros(3), camera(), loss_mask=left, draw_weight=draw_weight)


def test_edits_are_drawn_by_their_draw_weights():
    """An edit with draw weight 0 is never drawn: only the other edit's masked region changes."""
    avatar = coloured_avatar()
    video = video_of(avatar)
    ignored = left_half_edit(video, [1.0, 0.0, 0.0], draw_weight=0.0)
    drawn = left_half_edit(video, [0.0, 0.0, 1.0])
    config = TrainConfig(iterations=40, edit_probability=1.0)
    config.learning_rates.sh_dc = 0.05
    train(avatar, video, [ignored, drawn], config=config, progress=False)
    with torch.no_grad():
        after = render_avatar(avatar, yaw(0.0), torch.zeros(3), camera(), torch.ones(3)).image
    inside = video[0].foreground & drawn.loss_mask
    blue_share = after[inside][:, 2].mean() - after[inside][:, 0].mean()
    assert blue_share > 0.3, float(blue_share)


def test_edit_steps_leave_the_frozen_parameters_unchanged():
    avatar = coloured_avatar()
    video = video_of(avatar)
    edit = left_half_edit(video, [1.0, 0.0, 0.0])
    initial = {name: value.detach().clone() for name, value in avatar.params.items()}
    frozen = ("means", "quats", "log_scales")
    config = TrainConfig(iterations=10, edit_probability=1.0, edit_frozen=frozen, densify=UNBOUNDED)
    train(avatar, video, [edit], config=config, progress=False)
    for name in frozen:
        assert torch.equal(avatar.params[name], initial[name]), name
    assert not torch.equal(avatar.params["sh_dc"], initial["sh_dc"])
    # the same steps drawing video frames do move them
    train(avatar, video, [edit], config=TrainConfig(iterations=10, edit_probability=0.0, edit_frozen=frozen), progress=False)
    assert not torch.equal(avatar.params["means"], initial["means"])


def test_background_alpha_sums_the_edit_background_over_all_pixels():
    alpha = torch.rand(6, 5, dtype=torch.float64)
    mask = torch.zeros(6, 5, dtype=torch.bool)
    mask[1:4, 1:3] = True
    foreground = torch.zeros(6, 5, dtype=torch.bool)
    foreground[1, 1] = True
    expected = sum(float(alpha[y, x]) for y in range(6) for x in range(5) if mask[y, x] and not foreground[y, x]) / 30
    assert math.isclose(float(background_alpha(alpha, mask, foreground)), expected, rel_tol=1e-12)


def test_background_alpha_weight_clears_a_background_edit_faster():
    """A background edit (left half: nothing here) against a sphere whose colour is close to the random
    backgrounds' mean: the alpha term clears more of the region than the colour loss alone."""
    grey = Avatar.from_template(sphere_template(), sh_degree=1)
    grey.params["sh_dc"].data = rgb_to_sh(torch.full((len(grey), 3), 0.5))[:, None, :]
    video = video_of(grey)
    left = torch.zeros(SIZE, SIZE, dtype=torch.bool)
    left[:, : SIZE // 2] = True
    edit = TrainingView(torch.ones(SIZE, SIZE, 3), torch.zeros(SIZE, SIZE, dtype=torch.bool), yaw(0.0), torch.zeros(3), camera(), loss_mask=left)
    remaining = []
    for weight in (0.0, 4.0):
        avatar = Avatar.from_template(sphere_template(), sh_degree=1)
        avatar.params["sh_dc"].data = grey.params["sh_dc"].data.clone()
        train(avatar, video, [edit], config=TrainConfig(iterations=100, edit_probability=1.0, background_alpha_weight=weight), progress=False)
        with torch.no_grad():
            alpha = render_avatar(avatar, yaw(0.0), torch.zeros(3), camera(), torch.ones(3)).alpha
        remaining.append(float(alpha[left & video[0].foreground].mean()))
    assert remaining[1] < 0.9 * remaining[0], remaining




def test_edit_loss_weight_leaves_what_only_the_edits_supervise_as_fast():
    """Adam divides each step by the gradients' own size: on edit steps alone the weight changes nothing,
    but for the few entries whose gradients are as small as its eps (1e-15)."""
    results = []
    for weight in (1.0, 0.25):
        avatar = coloured_avatar()
        video = video_of(avatar)
        config = TrainConfig(iterations=15, edit_probability=1.0, edit_loss_weight=weight, densify=UNBOUNDED)
        train(avatar, video, [left_half_edit(video, [1.0, 0.0, 0.0])], config=config, progress=False)
        results.append(avatar)
    for name, value in results[0].params.items():
        differs = ~torch.isclose(results[1].params[name], value, rtol=1e-4, atol=1e-6)
        assert differs.double().mean() < 0.01, (name, int(differs.sum()))
    assert not torch.equal(results[0].params["sh_dc"], coloured_avatar().params["sh_dc"]), "the edit steps should move the avatar"


def test_edit_loss_weight_lets_the_video_outweigh_an_edit_it_contradicts():
    """The video shows the sphere's own colours; an edit paints half of one view red. Mixed steps: with the
    edit's loss at a quarter, the video's frames stay closer to the video and the half less red."""
    video = video_of(coloured_avatar())
    edit = left_half_edit(video, [1.0, 0.0, 0.0])
    inside = video[0].foreground & edit.loss_mask
    fits, reds = [], []
    for weight in (1.0, 0.25):
        avatar = coloured_avatar()
        config = TrainConfig(iterations=80, edit_probability=0.5, edit_loss_weight=weight)
        config.learning_rates.sh_dc = 0.05
        train(avatar, video, [edit], config=config, progress=False)
        fits.append(mean_psnr(avatar, video))
        with torch.no_grad():
            image = render_avatar(avatar, yaw(0.0), torch.zeros(3), camera(), torch.ones(3)).image
        reds.append(float(image[inside][:, 0].mean() - image[inside][:, 1:].mean()))
    assert fits[1] > fits[0] + 1.0, fits
    assert reds[1] < reds[0], reds


def test_an_edit_views_loss_weight_multiplies_the_edit_loss_weight():
    """A strong edit's view weighs its loss on top of the configured edit weight: 0.25 x 4 trains as 1 x 1."""
    video = video_of(coloured_avatar())
    edit = left_half_edit(video, [1.0, 0.0, 0.0])
    results = []
    for config_weight, view_weight in ((1.0, 1.0), (0.25, 4.0), (0.25, 1.0)):
        avatar = coloured_avatar()
        config = TrainConfig(iterations=20, edit_probability=0.5, edit_loss_weight=config_weight)
        train(avatar, video, [replace(edit, loss_weight=view_weight)], config=config, progress=False)
        results.append(avatar.params["sh_dc"].detach())
    assert torch.equal(results[0], results[1])
    assert not torch.equal(results[0], results[2])


def test_rate_scales_set_each_gaussians_learning_rate():
    """A factor 0 leaves a Gaussian's parameter where it was; the others train."""
    video = video_of(coloured_avatar())
    target = Avatar.from_template(sphere_template(), sh_degree=1)  # grey: every colour must change
    frozen = torch.zeros(len(target), dtype=torch.bool)
    frozen[::2] = True
    scales = {"sh_dc": (~frozen).float()}
    train(target, video, config=TrainConfig(iterations=10), progress=False, rate_scales=scales)
    moved = (target.params["sh_dc"].detach() - rgb_to_sh(torch.full((3,), 0.5))).abs().amax(dim=(1, 2)) > 0
    assert not moved[frozen].any()
    assert moved[~frozen].float().mean() > 0.5


def test_the_mask_band_keeps_a_dilated_masks_ring_empty():
    """Masks 2 px too wide around a sphere on white: without the band the trainer paints the ring white
    (the mask calls it subject); with it the frame's white there reads as background and the ring stays
    nearly empty."""
    truth = video_of(coloured_avatar())
    kernel = torch.ones(1, 1, 5, 5)
    dilated = [
        replace(view, foreground=torch.nn.functional.conv2d(view.foreground[None, None].float(), kernel, padding=2)[0, 0] > 0)
        for view in truth
    ]
    ring = dilated[0].foreground & ~truth[0].foreground
    alphas = []
    for band in (0, 3):
        avatar = coloured_avatar()
        train(avatar, dilated, config=TrainConfig(iterations=60, mask_band=band, densify=UNBOUNDED), progress=False)
        with torch.no_grad():
            alphas.append(float(render_avatar(avatar, yaw(0.0), torch.zeros(3), camera(), torch.ones(3)).alpha[ring].mean()))
    assert alphas[1] < 0.5 * alphas[0], alphas


def test_a_backdrop_every_view_shares_is_moved_once():
    """Moving the views to a device copies the video's shared backdrop once, not once per frame."""
    backdrop = torch.rand(SIZE, SIZE, 3)
    views = [replace(view, backdrop=backdrop) for view in video_of(coloured_avatar(), frames=3)]
    views.append(replace(views[0], backdrop=torch.rand(SIZE, SIZE, 3)))  # another video's backdrop
    moved: dict[int, torch.Tensor] = {}
    on_meta = [view.to(torch.device("meta"), moved) for view in views]
    assert all(view.backdrop.device.type == "meta" for view in on_meta)
    assert on_meta[0].backdrop is on_meta[1].backdrop is on_meta[2].backdrop
    assert on_meta[3].backdrop is not on_meta[0].backdrop
    assert len(moved) == 2


def test_the_progress_bar_compares_what_the_loss_compares(monkeypatch):
    """In the mask band the loss compares the render over the backdrop with the frame; the bar's PSNR must
    read that render, not the one over the step's random background (which reads as a 13 dB avatar)."""
    shown = []
    monkeypatch.setattr(TrainingProgress, "update", lambda self, loss, image, target, count: shown.append((image, target)))
    video = video_of(coloured_avatar())
    train(coloured_avatar(), video, config=TrainConfig(iterations=4, mask_band=3, densify=UNBOUNDED), progress=False)
    band_outside_subject = boundary_band(video[0].foreground, 3) & ~video[0].foreground
    for image, target in shown:
        rows, cols = subject_bbox(video[0].foreground, TrainConfig.bbox_margin)
        empty = band_outside_subject[rows, cols]
        assert empty.any()
        assert psnr(image[empty], target[empty]) > 30
