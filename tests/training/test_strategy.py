import math

import pytest
import torch

from avatarperfect_cli.body import axis_angle_to_matrix, matrix_to_quaternion, quaternion_to_matrix
from avatarperfect_cli.render import RenderOutput
from avatarperfect_cli.training.optim import LearningRates, create_optimizers
from avatarperfect_cli.training.strategy import DensifyConfig, DensifyStrategy, RefineStats, bound_scales, split_children

WIDTH, HEIGHT = 200, 100


def make_params(n: int, seed: int = 0) -> dict[str, torch.nn.Parameter]:
    generator = torch.Generator().manual_seed(seed)
    sh_dc = torch.zeros(n, 1, 3)
    sh_dc[:, 0, 0] = torch.arange(n, dtype=torch.float32)  # marks each Gaussian's origin
    values = {
        "means": torch.randn(n, 3, generator=generator) * 0.1,
        "quats": torch.nn.functional.normalize(torch.randn(n, 4, generator=generator), dim=-1),
        "log_scales": torch.full((n, 3), math.log(0.002)),
        "opacity_logits": torch.full((n,), 2.0),
        "sh_dc": sh_dc,
        "sh_rest": torch.randn(n, 3, 3, generator=generator),
        "skin_logits": torch.randn(n, 24, generator=generator),
    }
    return {name: torch.nn.Parameter(value) for name, value in values.items()}


def run_step(strategy, params, optimizers, state, step, screen_grad, radii, optimizer_step=True):
    """One training step whose loss has d loss / d means2d = screen_grad (N, 2), pixels^-1."""
    means2d = params["means"][:, :2] * 1.0  # a non-leaf in the graph, as the rasterizer's
    n = means2d.shape[0]
    out = RenderOutput(
        torch.zeros(HEIGHT, WIDTH, 3), torch.zeros(HEIGHT, WIDTH), None, torch.zeros(n), means2d, radii, WIDTH, HEIGHT
    )
    strategy.step_pre_backward(params, optimizers, state, step, out)
    loss = (means2d * screen_grad).sum() + 1e-3 * sum(p.sum() for p in params.values())
    loss.backward()
    stats = strategy.step_post_backward(params, optimizers, state, step, out)
    if optimizer_step:
        for optimizer in optimizers.values():
            optimizer.step()
            optimizer.zero_grad()
    return stats


def test_gart_refine_schedule() -> None:
    strategy = DensifyStrategy()
    assert [s for s in range(1000) if strategy.is_refine_step(s)] == [101, 302, 503, 704]


def test_accumulates_ndc_normalised_gradient_norms_of_drawn_gaussians() -> None:
    params = make_params(3)
    optimizers = create_optimizers(params, LearningRates())
    strategy = DensifyStrategy(DensifyConfig(refine_start=100))
    state = strategy.initialize_state()
    screen_grad = torch.tensor([[3e-6, 4e-6], [1e-6, 0.0], [5e-6, 5e-6]])
    radii = torch.tensor([2, 1, 0], dtype=torch.int32)
    for step in range(2):
        assert run_step(strategy, params, optimizers, state, step, screen_grad, radii) is None
    expected = torch.tensor([math.hypot(3e-6 * 100, 4e-6 * 50), 1e-6 * 100, 0.0]) * 2
    torch.testing.assert_close(state.grad_norm_sum, expected)
    torch.testing.assert_close(state.visible_count, torch.tensor([2.0, 2.0, 0.0]))


def test_clone_split_prune_keep_params_and_adam_state_consistent() -> None:
    params = make_params(6)
    with torch.no_grad():
        params["log_scales"][1] = torch.log(torch.tensor([0.05, 0.01, 0.003]))  # large: split
        params["opacity_logits"][2] = -3.0  # opacity 0.047: pruned
    optimizers = create_optimizers(params, LearningRates(skin_start=0))
    strategy = DensifyStrategy(DensifyConfig(refine_start=1, refine_every=10, refine_stop=50, grad_threshold=1e-4))
    state = strategy.initialize_state()
    high, low = 1e-5, 1e-8  # normalised: about 1e-3 and 1e-6, against the threshold 1e-4
    screen_grad = torch.tensor([[high, 0], [high, 0], [high, 0], [low, 0], [high, 0], [low, low]])
    radii = torch.tensor([3, 3, 3, 3, 0, 3], dtype=torch.int32)  # Gaussian 4 is never drawn
    run_step(strategy, params, optimizers, state, 0, screen_grad, radii)

    before = {name: param.detach().clone() for name, param in params.items()}
    moments = {name: dict(optimizers[name].state[param]) for name, param in params.items()}
    moments = {name: {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in m.items()} for name, m in moments.items()}
    stats = run_step(strategy, params, optimizers, state, 1, screen_grad, radii, optimizer_step=False)

    assert stats == RefineStats(cloned=1, split=1, pruned=1, total=7)
    assert state.grad_norm_sum is None
    origin = params["sh_dc"][:, 0, 0].round().long().tolist()
    assert origin == [0, 3, 4, 5, 0, 1, 1]  # kept rows in order, then the clone, then the two children
    kept = torch.tensor([0, 3, 4, 5])
    for name, param in params.items():
        assert param.shape[0] == 7
        optimizer = optimizers[name]
        assert optimizer.param_groups[0]["params"] == [param]
        adam_state = optimizer.state[param]
        for key in ("exp_avg", "exp_avg_sq"):
            assert adam_state[key].shape == param.shape
            torch.testing.assert_close(adam_state[key][:4], moments[name][key][kept])
            assert not adam_state[key][4:].any()
        assert adam_state["step"] == moments[name]["step"]
        torch.testing.assert_close(param[:4], before[name][kept])
        torch.testing.assert_close(param[4], before[name][0])  # the clone copies its parent
        if name not in ("means", "log_scales"):
            torch.testing.assert_close(param[5:], before[name][[1, 1]])  # children copy the rest
    torch.testing.assert_close(params["log_scales"][5:], (before["log_scales"][1] - math.log(1.6)).expand(2, 3))
    assert (params["means"][5:] - before["means"][1]).norm(dim=-1).max() < 5 * 0.05

    # the optimizers still step, and move every parameter
    for param in params.values():
        param.grad = torch.ones_like(param)
    for optimizer in optimizers.values():
        optimizer.step()
    for name, param in params.items():
        assert (param[:4] != before[name][kept]).all()


def test_densification_keeps_per_row_rate_factors_in_step() -> None:
    params = make_params(6)
    with torch.no_grad():
        params["log_scales"][1] = torch.log(torch.tensor([0.05, 0.01, 0.003]))  # large: split
        params["opacity_logits"][2] = -3.0  # pruned
    factors = torch.arange(6, dtype=torch.float32) + 10.0
    optimizers = create_optimizers(params, LearningRates(skin_start=0), row_scales={"means": factors})
    strategy = DensifyStrategy(DensifyConfig(refine_start=1, refine_every=10, refine_stop=50, grad_threshold=1e-4))
    state = strategy.initialize_state()
    high, low = 1e-5, 1e-8
    screen_grad = torch.tensor([[high, 0], [high, 0], [high, 0], [low, 0], [high, 0], [low, low]])
    radii = torch.tensor([3, 3, 3, 3, 0, 3], dtype=torch.int32)
    run_step(strategy, params, optimizers, state, 0, screen_grad, radii)
    run_step(strategy, params, optimizers, state, 1, screen_grad, radii)
    # rows kept (0, 3, 4, 5) keep their factors; the clone and the two children start at 1
    torch.testing.assert_close(optimizers["means"].param_groups[0]["row_scale"], torch.tensor([10.0, 13, 14, 15, 1, 1, 1]))
    assert "row_scale" not in optimizers["quats"].param_groups[0]


def test_split_children_sample_the_parent_in_its_local_frame() -> None:
    n = 200
    params = make_params(n)
    rotation = axis_angle_to_matrix(torch.tensor([0.4, -1.2, 0.9]))
    scales = torch.tensor([0.05, 0.01, 0.002])
    with torch.no_grad():
        params["quats"][:] = matrix_to_quaternion(rotation)
        params["log_scales"][:] = torch.log(scales)
    optimizers = create_optimizers(params, LearningRates())
    strategy = DensifyStrategy(DensifyConfig(refine_start=0, clone_max_scale=0.001, max_scale=0.0), seed=1)
    state = strategy.initialize_state()
    parents = params["means"].detach().clone()
    screen_grad = torch.full((n, 2), 1e-5)
    stats = run_step(strategy, params, optimizers, state, 0, screen_grad, torch.ones(n, dtype=torch.int32), False)
    assert stats == RefineStats(cloned=0, split=n, pruned=0, total=2 * n)
    children = params["means"].detach().reshape(2, n, 3)
    local = (children - parents) @ rotation / scales  # offsets in the parent's frame, in its standard deviations
    assert local.abs().max() < 5.0
    std = local.reshape(-1, 3).std(dim=0)
    assert ((std > 0.85) & (std < 1.15)).all(), std
    torch.testing.assert_close(quaternion_to_matrix(params["quats"][:1])[0], rotation, atol=1e-6, rtol=0)


def test_split_children_copy_their_parent_with_smaller_scales() -> None:
    params = {name: param.detach() for name, param in make_params(5).items()}
    split = torch.tensor([True, False, True, False, False])
    children = split_children(params, split, 1.6, torch.Generator().manual_seed(0))
    assert set(children) == set(params)
    for name in ("quats", "opacity_logits", "sh_dc", "sh_rest", "skin_logits"):
        torch.testing.assert_close(children[name], torch.cat([params[name][split]] * 2), rtol=0, atol=0)
    torch.testing.assert_close(children["log_scales"], torch.cat([params["log_scales"][split]] * 2) - math.log(1.6))
    offsets = children["means"] - torch.cat([params["means"][split]] * 2)
    assert offsets.shape == (4, 3) and (offsets.norm(dim=-1) > 0).all() and offsets.norm(dim=-1).max() < 5 * math.sqrt(3) * 0.002
    assert not torch.equal(offsets[:2], offsets[2:]), "the two children of a parent are two samples"


def test_growth_stops_at_max_gaussians_keeping_the_largest_gradients() -> None:
    params = make_params(6)
    with torch.no_grad():
        params["opacity_logits"][5] = -4.0  # pruned
    optimizers = create_optimizers(params, LearningRates())
    strategy = DensifyStrategy(DensifyConfig(refine_start=0, max_gaussians=7))
    state = strategy.initialize_state()
    screen_grad = torch.tensor([[1e-5, 0], [4e-5, 0], [1e-8, 0], [3e-5, 0], [2e-5, 0], [9e-5, 0]])
    radii = torch.ones(6, dtype=torch.int32)
    stats = run_step(strategy, params, optimizers, state, 0, screen_grad, radii)
    assert stats == RefineStats(cloned=2, split=0, pruned=1, total=7)
    assert params["sh_dc"][:, 0, 0].round().long().tolist() == [0, 1, 2, 3, 4, 1, 3]


def test_opacity_reset_clamps_opacities_and_clears_their_moments() -> None:
    params = make_params(4)
    with torch.no_grad():
        params["opacity_logits"][0] = -2.0  # 0.12, below the reset value 0.2
    optimizers = create_optimizers(params, LearningRates())
    strategy = DensifyStrategy(DensifyConfig(refine_start=100, reset_opacity_every=3))
    state = strategy.initialize_state()
    radii = torch.ones(4, dtype=torch.int32)
    for step in range(3):
        run_step(strategy, params, optimizers, state, step, torch.zeros(4, 2), radii)
    assert (torch.sigmoid(params["opacity_logits"][1:]) > 0.8).all()
    run_step(strategy, params, optimizers, state, 3, torch.zeros(4, 2), radii, optimizer_step=False)
    opacities = torch.sigmoid(params["opacity_logits"])
    torch.testing.assert_close(opacities[1:], torch.full((3,), 0.2))
    assert opacities[0] < 0.13
    assert not optimizers["opacity_logits"].state[params["opacity_logits"]]["exp_avg"].any()


def test_post_backward_without_pre_backward_is_an_error() -> None:
    params = make_params(2)
    optimizers = create_optimizers(params, LearningRates())
    strategy = DensifyStrategy()
    means2d = params["means"][:, :2] * 1.0
    out = RenderOutput(torch.zeros(1, 1, 3), torch.zeros(1, 1), None, torch.zeros(2), means2d, torch.ones(2), 1, 1)
    means2d.sum().backward()
    with pytest.raises(RuntimeError, match="step_pre_backward"):
        strategy.step_post_backward(params, optimizers, strategy.initialize_state(), 0, out)
    assert strategy.step_post_backward(params, optimizers, strategy.initialize_state(), 800, out) is None


def test_densify_an_avatar_rendered_by_the_rasterizer() -> None:
    from avatarperfect_cli.avatar.model import Avatar
    from avatarperfect_cli.body import BodyTemplate
    from avatarperfect_cli.render import Camera, look_at, rasterization
    from avatarperfect_cli.training.losses import image_loss

    vertices = torch.tensor([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]) * 0.3
    faces = torch.tensor([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    weights = torch.zeros(6, 24)
    weights[:, 0] = 1.0
    avatar = Avatar.from_template(BodyTemplate(vertices.float(), faces, weights, torch.zeros(24, 3)))
    K = torch.tensor([[80.0, 0, 32], [0, 80, 32], [0, 0, 1]])
    camera = Camera(K, look_at(torch.tensor([0.0, 0, 2]), torch.zeros(3), torch.tensor([0.0, 1, 0])), 64, 64)
    target = torch.ones(64, 64, 3) * torch.tensor([0.8, 0.2, 0.2])
    optimizers = create_optimizers(avatar.params, LearningRates())
    config = DensifyConfig(refine_start=1, refine_every=10, clone_max_scale=0.05, max_scale=0.0)
    strategy = DensifyStrategy(config)
    state = strategy.initialize_state()
    for step in range(3):
        means, quats = avatar.pose(torch.zeros(24, 3), torch.zeros(3))
        out = rasterization(means, quats, avatar.scales, avatar.opacities, avatar.sh, camera, sh_degree=0)
        strategy.step_pre_backward(avatar.params, optimizers, state, step, out)
        image_loss(out.image, target).backward()
        stats = strategy.step_post_backward(avatar.params, optimizers, state, step, out)
        if step == 0:
            # the four rim discs move the silhouette; the centred front and hidden back ones barely do
            assert (state.grad_norm_sum[:4] > 1e-3).all() and (state.grad_norm_sum[4:] < 1e-5).all()
            assert (state.visible_count == 1).all()
        if step == 1:
            assert stats == RefineStats(cloned=0, split=4, pruned=0, total=10)
        for optimizer in optimizers.values():
            optimizer.step()
            optimizer.zero_grad()
    assert len(avatar) == 10 and avatar.skin_weights.shape == (10, 24)


def test_bound_scales_clamps_length_and_needles_but_not_discs() -> None:
    scales = torch.tensor([
        [0.010, 0.0005, 0.0005],  # a needle: 20 times longer than wide
        [0.040, 0.0400, 0.0010],  # a large flat disc
        [0.004, 0.0040, 0.0002],  # a small flat disc: unchanged
        [0.002, 0.0100, 0.0050],  # anisotropy 2: unchanged
    ])  # fmt: skip
    log_scales = scales.log()

    bound_scales(log_scales, max_scale=0.025, max_anisotropy=10.0)
    expected = torch.tensor([[0.005, 0.0005, 0.0005], [0.025, 0.025, 0.001], [0.004, 0.004, 0.0002], [0.002, 0.01, 0.005]])
    torch.testing.assert_close(log_scales.exp(), expected)
    unbounded = scales.log()
    bound_scales(unbounded, max_scale=0.0, max_anisotropy=0.0)
    torch.testing.assert_close(unbounded.exp(), scales)


def test_bound_scales_bounds_the_largest_by_the_sorted_second_largest() -> None:
    """Every axis order and ties: the anisotropy bound follows the second largest of a sort."""
    generator = torch.Generator().manual_seed(0)
    log_scales = torch.randn(2000, 3, generator=generator) * 2 - 5
    log_scales[:100, 1] = log_scales[:100, 0]  # ties
    expected = torch.minimum(log_scales, log_scales.sort(dim=-1).values[:, 1:2] + math.log(10.0))
    bound_scales(log_scales, max_scale=0.0, max_anisotropy=10.0)
    assert torch.equal(log_scales, expected)


def test_scales_stay_bounded_through_and_after_densification() -> None:
    params = make_params(6)
    optimizers = create_optimizers(params, LearningRates(skin_start=0))
    config = DensifyConfig(refine_start=5, refine_every=10, refine_stop=40, grad_threshold=1e-4)
    strategy = DensifyStrategy(config)
    state = strategy.initialize_state()
    for step in range(1000):  # a loss that stretches every Gaussian along its first axis, in the trainer's order
        means2d = params["means"][:, :2] * 1.0
        n = means2d.shape[0]
        out = RenderOutput(torch.zeros(HEIGHT, WIDTH, 3), torch.zeros(HEIGHT, WIDTH), None, torch.zeros(n), means2d,
                           torch.full((n,), 3, dtype=torch.int32), WIDTH, HEIGHT)  # fmt: skip
        strategy.step_pre_backward(params, optimizers, state, step, out)
        ((means2d * 1e-5).sum() - params["log_scales"][:, 0].sum()).backward()
        for optimizer in optimizers.values():
            optimizer.step()
            optimizer.zero_grad()
        strategy.step_post_backward(params, optimizers, state, step, out)
    scales = params["log_scales"].detach().exp()
    assert params["means"].shape[0] > 6  # densified
    assert scales.max() <= config.max_scale * (1 + 1e-6)
    sorted_scales = scales.sort(dim=-1).values
    assert (sorted_scales[:, 2] <= config.max_anisotropy * sorted_scales[:, 1] * (1 + 1e-6)).all()
    assert scales[:, 0].min() > 0.002 * 4  # they did grow, up to the bound
