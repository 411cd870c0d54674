"""Pose and camera suggestion: the orbit geometry, the objective's gradient against finite differences, and
`suggest_view` end to end on a small template avatar."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from avatarperfect_cli.avatar.model import Avatar, vertex_normals_and_areas
from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.body import forward_kinematics, load_body_template
from avatarperfect_cli.gaussians import sh_to_rgb
from avatarperfect_cli.io.pose_json import PoseFile
from avatarperfect_cli.refinement import suggest
from avatarperfect_cli.refinement.collision import BodyCapsules
from avatarperfect_cli.refinement.pose_prior import BuiltinPosePrior, joint_limit_violations, load_pose_prior
from avatarperfect_cli.refinement.suggest import (
    OrbitView,
    SuggestConfig,
    animation_exposure,
    exposure_relevance,
    suggest_view,
)
from avatarperfect_cli.refinement.visibility import gaussian_visibility, suggestion_weights
from avatarperfect_cli.render import rasterization
from avatarperfect_cli.sample.generate import fit_camera
from avatarperfect_cli.sample.motions import turntable

REFERENCE_POSE = torch.as_tensor(turntable(1).body_pose[0]).float()  # the sample video's A-pose, facing +Z
REFERENCE_TRANSL = torch.tensor([0.05, 0.9, -0.1])
UP = torch.tensor([0.0, 1.0, 0.0])


def template_avatar(every: int, scale: float, opacity: float | None = None) -> Avatar:
    """Every `every`-th Gaussian of the anny template avatar, `scale` times larger, random colours."""
    template = load_body_template("anny")
    full = Avatar.from_template(template, sh_degree=0)
    params = {name: param.detach()[::every].clone() for name, param in full.params.items()}
    params["log_scales"] += math.log(scale)
    if opacity is not None:
        params["opacity_logits"].fill_(math.log(opacity / (1 - opacity)))
    params["sh_dc"] = torch.randn(params["sh_dc"].shape, generator=torch.Generator().manual_seed(0))
    return Avatar(params, full.rest_joints, sh_degree=0)


def reference_view(avatar: Avatar, size: int) -> PoseFile:
    """The training pose seen by the sample's camera (in front of the body, on +Z, looking horizontally)."""
    means, _ = avatar.pose(REFERENCE_POSE, REFERENCE_TRANSL)
    return PoseFile(REFERENCE_POSE, REFERENCE_TRANSL, fit_camera(means.detach().double().numpy(), size))


def canonical_normals(every: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Canonical positions and unit normals of every `every`-th template vertex (the avatar's Gaussians)."""
    template = load_body_template("anny")
    normals, _ = vertex_normals_and_areas(template.vertices.float(), template.faces.long())
    return template.vertices[::every].float(), normals[::every]


def back_is_unseen(every: int) -> torch.Tensor:
    """(N,) float64 V: 1 for the Gaussians on the front of the body (canonical normal towards +Z), 0 on the back."""
    return (canonical_normals(every)[1][:, 2] > 0).double()


def joints_box_centre(avatar: Avatar, body_pose: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
    """(3,) float64 centre of the posed joints' bounding box (what the orbit turns about), metres."""
    transforms = forward_kinematics(body_pose[None].double(), avatar.rest_joints.double(), transl[None].double())[0]
    joints = transforms[:, :3, 3] + (transforms[:, :3, :3] @ avatar.rest_joints.double()[:, :, None])[..., 0]
    return 0.5 * (joints.min(dim=0).values + joints.max(dim=0).values)


def frozen_framing(monkeypatch: pytest.MonkeyPatch, view: OrbitView, latent: torch.Tensor, angles) -> None:
    """Hold the framing distance and the orbit centre at their values at (latent, angles).

    `render` recomputes both from the posed body (the camera follows the body); these tests check the
    gradient through the pose and the orbit with the framing held fixed, so finite differences must hold
    it too (the frozen distance carries no gradient).
    """
    distances: list[float] = []
    original = suggest.framing_distance

    def recording(*args) -> float:
        distances.append(original(*args))
        return distances[-1]

    monkeypatch.setattr(suggest, "framing_distance", recording)
    with torch.no_grad():
        view.render(latent, *angles, view.reference.camera, torch.zeros(len(view.avatar), 1))
        centre = view._body_center(view.avatar.joint_transforms(view.body_pose(latent), view.reference.transl))
    monkeypatch.setattr(suggest, "framing_distance", lambda *args: distances[0])
    monkeypatch.setattr(OrbitView, "_body_center", lambda self, transforms: centre)


# ---------------------------------------------------------------- orbit geometry


@pytest.fixture(scope="module")
def small_avatar() -> Avatar:
    return template_avatar(every=8, scale=2.5)


@pytest.mark.parametrize("azimuth_deg,elevation_deg", [(0.0, 0.0), (130.0, 35.0), (-60.0, -40.0)])
def test_orbit_pose_file_camera_renders_the_same_image(small_avatar: Avatar, azimuth_deg, elevation_deg) -> None:
    avatar = small_avatar
    reference = reference_view(avatar, 48)
    prior = load_pose_prior("builtin", REFERENCE_POSE)
    view = OrbitView(avatar, prior, reference, fill=0.9)
    latent = 0.7 * torch.randn(32, generator=torch.Generator().manual_seed(1))
    azimuth, elevation = torch.tensor(math.radians(azimuth_deg)), torch.tensor(math.radians(elevation_deg))
    colors = sh_to_rgb(avatar.params["sh_dc"].detach()[:, 0]).clamp_min(0.0)  # SH degree 0: view-independent
    with torch.no_grad():
        image, pose = view.render(latent, azimuth, elevation, reference.camera, colors)
        direct = render_avatar(avatar, pose.body_pose, pose.transl, pose.camera, torch.zeros(3)).image
        at_reference = render_avatar(avatar, pose.body_pose, pose.transl, reference.camera, torch.zeros(3)).image
    assert torch.equal(pose.body_pose, view.body_pose(latent)) and torch.equal(pose.transl, REFERENCE_TRANSL)
    assert torch.equal(pose.camera.K, reference.camera.K) and (pose.camera.width, pose.camera.height) == (48, 48)
    assert image.abs().sum() > 100.0
    # the two paths round differently in float32, which may push a Gaussian across alpha = 1/255 at a pixel
    difference = (direct - image).abs()
    assert float(difference.max()) < 0.02 and float((difference > 1e-4).float().mean()) < 1e-3
    assert (at_reference - image).abs().max() > 0.2, "the reference camera must not render the orbit image"

    # where the camera is: turned by the azimuth about +Y from the reference's bearing (+Z), raised by the elevation
    centre = joints_box_centre(avatar, pose.body_pose, pose.transl)
    offset = pose.camera.center.double() - centre
    distance = float(offset.norm())
    assert math.degrees(math.asin(float(offset[1]) / distance)) == pytest.approx(elevation_deg, abs=0.01)
    bearing = math.degrees(math.atan2(float(offset[0]), float(offset[2])))
    assert (bearing - azimuth_deg + 180.0) % 360.0 - 180.0 == pytest.approx(0.0, abs=0.01)
    # it looks at the centre, keeping the reference's up direction level (no roll)
    rotation = pose.camera.world_to_camera[:3, :3].double()
    torch.testing.assert_close(rotation[2], -offset / distance, rtol=0, atol=1e-5)
    assert abs(float(rotation[0] @ UP.double())) < 1e-5

    # framing: every posed centre projects inside the image, and the widest spans `fill` of it
    means, _ = avatar.pose(pose.body_pose, pose.transl)
    local = means.detach().double() @ rotation.T + pose.camera.world_to_camera[:3, 3].double()
    assert (local[:, 2] > 0.05).all()
    K = pose.camera.K.double()
    u = K[0, 0] * local[:, 0] / local[:, 2] + K[0, 2]
    v = K[1, 1] * local[:, 1] / local[:, 2] + K[1, 2]
    assert ((u >= 0) & (u <= 48) & (v >= 0) & (v <= 48)).all()
    reach = torch.stack([(u - K[0, 2]) / K[0, 2], (v - K[1, 2]) / K[1, 2]]).abs().max()
    assert float(reach) == pytest.approx(0.9, abs=1e-3)


def test_frame_gives_the_pose_file_render_gives_without_rasterizing(small_avatar: Avatar, monkeypatch: pytest.MonkeyPatch) -> None:
    """`frame` must give exactly `render`'s pose file, and must not rasterize."""
    reference = reference_view(small_avatar, 48)
    view = OrbitView(small_avatar, load_pose_prior("builtin", REFERENCE_POSE), reference, fill=0.9)
    latent = 0.7 * torch.randn(32, generator=torch.Generator().manual_seed(3))
    angles = torch.tensor(2.0), torch.tensor(-0.3)
    colors = torch.ones(len(small_avatar), 1)
    with torch.no_grad():
        _, rendered = view.render(latent, *angles, reference.camera, colors)
        monkeypatch.setattr(suggest, "rasterization", lambda *args, **kwargs: pytest.fail("frame rasterized"))
        framed = view.frame(latent, *angles, reference.camera).pose
    assert torch.equal(framed.body_pose, rendered.body_pose) and torch.equal(framed.transl, rendered.transl)
    assert torch.equal(framed.camera.world_to_camera, rendered.camera.world_to_camera)
    assert torch.equal(framed.camera.K, rendered.camera.K)



def test_framed_gaussians_are_seen_as_the_pose_file_shows_them(small_avatar: Avatar) -> None:
    """`animation_exposure` rasterizes the framed Gaussians with the framing camera rather than skinning
    the avatar again for the pose file: the two must see every Gaussian alike."""
    reference = reference_view(small_avatar, 48)
    view = OrbitView(small_avatar, load_pose_prior("builtin", REFERENCE_POSE), reference, fill=0.9)
    latent = 0.7 * torch.randn(32, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        framed = view.frame(latent, torch.tensor(1.2), torch.tensor(0.0), reference.camera)
        no_colors = framed.means.new_zeros(len(small_avatar), 1)
        seen = rasterization(framed.means, framed.quats, small_avatar.scales, small_avatar.opacities, no_colors, framed.camera)
    expected = gaussian_visibility(small_avatar, framed.pose)
    assert float(expected.sum()) > 100.0
    torch.testing.assert_close(seen.visibility.double(), expected, rtol=1e-3, atol=1e-3 * float(expected.max()))

# ---------------------------------------------------------------- gradients


def test_objective_gradient_is_the_chain_rule_through_the_posed_gaussians(
    monkeypatch: pytest.MonkeyPatch, small_avatar: Avatar
) -> None:
    """The autograd gradient w.r.t. every latent component and both angles equals (d objective / d posed
    means, quats) . (finite-difference d posed means, quats / d parameter): the orbit, world transform,
    decoder and skinning contribute every term with the right sign (the rasterizer's own gradient is
    checked against the dense reference in tests/render)."""
    reference = reference_view(small_avatar, 40)
    view = OrbitView(small_avatar, BuiltinPosePrior(REFERENCE_POSE), reference, fill=0.9)
    canonical = small_avatar.params["means"].detach().double()
    weights = suggestion_weights(torch.exp(5.0 * canonical[:, 1])).float()[:, None]  # most of the body below mean
    latent0 = 0.5 * torch.randn(32, generator=torch.Generator().manual_seed(2))
    angles0 = (torch.tensor(2.2), torch.tensor(0.3))
    frozen_framing(monkeypatch, view, latent0, angles0)
    captured: list[tuple] = []  # the arguments of every rasterization call inside `render`
    original = suggest.rasterization

    def recording(*args, **kwargs):
        captured.append(args)
        return original(*args, **kwargs)

    monkeypatch.setattr(suggest, "rasterization", recording)

    latent, azimuth, elevation = latent0.clone().requires_grad_(), *(a.clone().requires_grad_() for a in angles0)
    image, _ = view.render(latent, azimuth, elevation, reference.camera, weights)
    image.sum().backward()
    autograd = torch.cat([latent.grad, azimuth.grad[None], elevation.grad[None]]).double()

    means, quats, scales, opacities, _, camera = captured[0]
    means, quats = means.detach().requires_grad_(), quats.detach().requires_grad_()
    out = original(means, quats, scales.detach(), opacities.detach(), weights, camera)
    grad_means, grad_quats = torch.autograd.grad(out.image.sum(), [means, quats])

    class Posed(Exception):
        """Raised by the rasterizer stand-in: `render` stops once its posed Gaussians are known."""

    def stop_at_rasterization(means, quats, *args, **kwargs):
        raise Posed(means.double(), quats.double())

    monkeypatch.setattr(suggest, "rasterization", stop_at_rasterization)

    def posed(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.no_grad(), pytest.raises(Posed) as stopped:
            view.render(x[:32], x[32], x[33], reference.camera, weights)
        return stopped.value.args

    x0 = torch.cat([latent0, torch.stack(angles0)])
    step = 1e-3
    chain = torch.zeros(34, dtype=torch.float64)
    for k in range(34):
        shift = torch.zeros(34)
        shift[k] = step
        (means_plus, quats_plus), (means_minus, quats_minus) = posed(x0 + shift), posed(x0 - shift)
        chain[k] = (grad_means.double() * (means_plus - means_minus)).sum() / (2 * step)
        chain[k] += (grad_quats.double() * (quats_plus - quats_minus)).sum() / (2 * step)
    scale = float(chain.abs().max())
    assert (chain.abs() > 0.01 * scale).sum() >= 20, "many components should matter"
    torch.testing.assert_close(autograd, chain, rtol=1e-2, atol=1e-4 * scale)


def test_objective_gradient_matches_finite_differences(monkeypatch: pytest.MonkeyPatch) -> None:
    """End to end: autograd d objective / d (z_k, azimuth, elevation) against finite differences of the rendered
    objective, on a smooth scene (few large Gaussians).

    A 3DGS image jumps where two overlapping Gaussians swap depth order or a footprint crosses alpha = 1/255;
    the gradient describes the smooth part between jumps. The finite difference is therefore the median of
    10 forward differences over [-5h, 5h], which steps over the (rare, at this scale) jumps; components whose
    forward differences still scatter (interquartile range > 10% of the median) are not compared.
    """
    avatar = template_avatar(every=300, scale=60.0, opacity=0.99)
    reference = reference_view(avatar, 48)
    view = OrbitView(avatar, BuiltinPosePrior(REFERENCE_POSE), reference, fill=0.9)
    canonical = avatar.params["means"].detach().double()
    weights = suggestion_weights(torch.exp(5.0 * canonical[:, 1])).float()[:, None]  # most of the body below mean
    latent0 = 0.5 * torch.randn(32, generator=torch.Generator().manual_seed(0))
    angles0 = (torch.tensor(2.2), torch.tensor(0.3))
    frozen_framing(monkeypatch, view, latent0, angles0)

    latent, azimuth, elevation = latent0.clone().requires_grad_(), *(a.clone().requires_grad_() for a in angles0)
    image, _ = view.render(latent, azimuth, elevation, reference.camera, weights)
    image.sum().backward()
    autograd = torch.cat([latent.grad, azimuth.grad[None], elevation.grad[None]]).double()

    def objective(x: torch.Tensor) -> float:
        with torch.no_grad():
            return float(view.render(x[:32], x[32], x[33], reference.camera, weights)[0].sum())

    # spine, neck, both shoulders and hips, azimuth and elevation
    components = [0, 2, 6, 9, 11, 17, 21, 28, 32, 33]
    x0 = torch.cat([latent0, torch.stack(angles0)])
    step = 2e-3
    compared = []
    for k in components:
        shift = torch.zeros(34)
        shift[k] = step
        slopes = np.diff([objective(x0 + j * shift) for j in range(-5, 6)]) / step
        median = float(np.median(slopes))
        quartiles = np.percentile(slopes, [25, 75])
        if quartiles[1] - quartiles[0] > 0.1 * abs(median):
            continue
        compared.append(k)
        assert float(autograd[k]) == pytest.approx(median, rel=0.08), f"component {k}"
    assert len(compared) >= 8 and {32, 33} <= set(compared), f"too few reliable finite differences: {compared}"


# ---------------------------------------------------------------- suggest_view end to end


@pytest.fixture(scope="module")
def setup(small_avatar: Avatar):
    """avatar, V (the back unseen), prior, capsules, reference (40 px, so the search's resolution is full size)."""
    template = load_body_template("anny")
    capsules = BodyCapsules.from_points(template.vertices, template.weights, template.rest_joints)
    reference = reference_view(small_avatar, 40)
    return small_avatar, back_is_unseen(every=8), BuiltinPosePrior(REFERENCE_POSE), capsules, reference


def run(setup, **settings) -> suggest.Suggestion:
    """A small search; the paper's objective (no exposure weighting) unless `settings` say otherwise."""
    avatar, visibility, prior, capsules, reference = setup
    config = SuggestConfig(**{"starts": 2, "candidates": 6, "steps": 4, "resolution": 40, "exposure_poses": 0, **settings})
    return suggest_view(avatar, visibility, prior, capsules, reference, config)


@pytest.fixture(scope="module")
def optimised(setup) -> suggest.Suggestion:
    return run(setup, body_pose="optimise", seed=0)


@pytest.fixture(scope="module")
def camera_only(setup) -> suggest.Suggestion:
    return run(setup, body_pose="canonical", seed=0)


def true_objective(setup, result: suggest.Suggestion) -> float:
    """sum_i clip(V_i - mean V) * sigma_i of the result's pose file, at full size."""
    avatar, visibility = setup[:2]
    return float((suggestion_weights(visibility) * gaussian_visibility(avatar, result.pose)).sum())


def test_suggestion_is_deterministic_for_a_seed(setup, optimised) -> None:
    again = run(setup, body_pose="optimise", seed=0)
    assert torch.equal(again.latent, optimised.latent)
    assert (again.azimuth, again.elevation) == (optimised.azimuth, optimised.elevation)
    assert again.objective == optimised.objective
    assert torch.equal(again.pose.body_pose, optimised.pose.body_pose)
    assert torch.equal(again.pose.camera.world_to_camera, optimised.pose.camera.world_to_camera)


def test_objective_is_the_documented_sum_for_the_returned_pose(setup, optimised) -> None:
    assert optimised.objective == pytest.approx(true_objective(setup, optimised), rel=1e-3)
    assert optimised.objective < 0


def test_optimising_never_ends_worse_than_the_best_start(setup, optimised) -> None:
    start = run(setup, body_pose="optimise", seed=0, steps=0)  # no steps: the best scored start itself
    assert optimised.objective <= start.objective
    assert setup[3].intersecting_pairs(optimised.pose.body_pose) == []
    assert joint_limit_violations(optimised.pose.body_pose) == []


def test_canonical_mode_keeps_the_reference_pose_exactly(setup, camera_only) -> None:
    reference, result = setup[4], camera_only
    assert torch.equal(result.pose.body_pose, reference.body_pose)
    assert torch.equal(result.pose.transl, reference.transl)
    assert torch.equal(result.latent, torch.zeros(32))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_mode_gives_a_natural_collision_free_pose(setup, seed: int) -> None:
    capsules, reference = setup[3], setup[4]
    result = run(setup, body_pose="random", seed=seed)
    assert joint_limit_violations(result.pose.body_pose) == []
    assert capsules.intersecting_pairs(result.pose.body_pose) == []
    assert (result.pose.body_pose - reference.body_pose).abs().max() > 0.1, "a random pose, not the reference"
    assert result.objective == pytest.approx(true_objective(setup, result), rel=1e-3)


@pytest.mark.parametrize("mode", ["canonical", "optimise"])
def test_an_unseen_back_is_shown_from_behind(setup, optimised, camera_only, mode: str) -> None:
    """V low exactly on the back (the reference camera sees the front): the camera goes behind the body."""
    avatar, _, _, _, reference = setup
    result = optimised if mode == "optimise" else camera_only
    assert abs(math.degrees(result.azimuth) - 180.0) < 45.0
    centre = joints_box_centre(avatar, result.pose.body_pose, result.pose.transl)
    reference_forward = reference.camera.world_to_camera[2, :3].double()  # the reference looks at the body's front
    assert float((result.pose.camera.center.double() - centre) @ reference_forward) > 1.0


def test_unknown_body_pose_mode_is_refused(setup) -> None:
    with pytest.raises(ValueError, match="body_pose"):
        run(setup, body_pose="dance")


# ---------------------------------------------------------------- weighting by what animations show


@pytest.fixture(scope="module")
def exposure(setup) -> torch.Tensor:
    avatar, _, prior, capsules, reference = setup
    view = OrbitView(avatar, prior, reference, SuggestConfig().fill)
    return animation_exposure(view, prior, capsules, reference.camera, poses=24, seed=0)


def test_animations_show_the_soles_less_than_the_chest(exposure: torch.Tensor) -> None:
    """Gaussians facing the floor at the feet are shown far less by natural poses seen from the camera's
    height than those on the front of the chest (on this coarse avatar about a third as much)."""
    positions, normals = canonical_normals(every=8)
    height = positions[:, 1]
    low, high = float(height.min()), float(height.max())
    soles = (normals[:, 1] < -0.8) & (height < low + 0.05)
    chest = (normals[:, 2] > 0.8) & (height > low + 0.7 * (high - low)) & (height < low + 0.8 * (high - low))
    assert soles.sum() >= 5 and chest.sum() >= 5
    assert float(exposure[soles].mean()) < 0.5 * float(exposure[chest].mean())
    relevance = exposure_relevance(exposure)
    assert float(relevance.max()) == 1.0 and float(relevance.min()) >= 0.0
    assert float(relevance[soles].mean()) < float(relevance[chest].mean())


def test_objective_with_exposure_is_the_documented_sum(setup, exposure: torch.Tensor) -> None:
    """sum_i clip(V_i - mean V) * r_i * sigma_i for the returned pose, with E measured as the search does."""
    avatar, visibility = setup[:2]
    result = run(setup, body_pose="optimise", seed=0, exposure_poses=24)
    weights = suggestion_weights(visibility) * exposure_relevance(exposure)
    assert result.objective == pytest.approx(float((weights * gaussian_visibility(avatar, result.pose)).sum()), rel=1e-3)
