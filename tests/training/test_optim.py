import math

import pytest
import torch

from avatarperfect_cli.training import optim
from avatarperfect_cli.training.optim import (
    ADAM_EPS, Adam, LearningRates, create_optimizers, exponential_decay, set_learning_rates,
)


def test_exponential_decay_is_log_linear() -> None:
    assert exponential_decay(0, 0, 100, 1e-2, 1e-4) == pytest.approx(1e-2)
    assert exponential_decay(50, 0, 100, 1e-2, 1e-4) == pytest.approx(1e-3)  # geometric mean
    assert exponential_decay(100, 0, 100, 1e-2, 1e-4) == pytest.approx(1e-4)
    assert exponential_decay(500, 0, 100, 1e-2, 1e-4) == pytest.approx(1e-4)
    assert exponential_decay(-5, 0, 100, 1e-2, 1e-4) == pytest.approx(1e-2)


def test_gart_learning_rates() -> None:
    rates = LearningRates(total_steps=2000)
    assert rates.at("means", 0) == pytest.approx(1.6e-4)
    assert rates.at("means", 1000) == pytest.approx(1.6e-5)
    assert rates.at("means", 2000) == pytest.approx(1.6e-6)
    assert rates.at("skin_logits", 499) == 0.0
    assert rates.at("skin_logits", 500) == pytest.approx(1e-4)
    assert rates.at("skin_logits", 1250) == pytest.approx(math.sqrt(1e-4 * 1e-5))
    assert rates.at("opacity_logits", 1234) == 0.05
    assert rates.at("sh_rest", 7) == 2.5e-4
    with pytest.raises(ValueError):
        rates.at("colour", 0)


def test_one_adam_per_parameter_follows_the_schedule() -> None:
    params = {
        "means": torch.nn.Parameter(torch.zeros(4, 3)),
        "quats": torch.nn.Parameter(torch.ones(4, 4)),
        "skin_logits": torch.nn.Parameter(torch.zeros(4, 24)),
    }
    rates = LearningRates(total_steps=100, skin_start=10)
    optimizers = create_optimizers(params, rates)
    assert set(optimizers) == set(params)
    for name, optimizer in optimizers.items():
        assert len(optimizer.param_groups) == 1
        assert optimizer.param_groups[0]["params"] == [params[name]]
    assert optimizers["means"].param_groups[0]["lr"] == pytest.approx(1.6e-4)
    assert optimizers["skin_logits"].param_groups[0]["lr"] == 0.0
    set_learning_rates(optimizers, rates, 50)
    assert optimizers["means"].param_groups[0]["lr"] == pytest.approx(1.6e-5)
    assert optimizers["skin_logits"].param_groups[0]["lr"] > 0.0

    # one Adam step moves each parameter by about its learning rate, against the gradient sign
    for param in params.values():
        param.grad = torch.ones_like(param)
    for optimizer in optimizers.values():
        optimizer.step()
    assert torch.allclose(params["means"], torch.full((4, 3), -1.6e-5))
    assert torch.allclose(params["quats"], torch.full((4, 4), 1 - 5e-3))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("on_torch_ops", [False, True])
@pytest.mark.parametrize("eps", [ADAM_EPS, 1e-8])
def test_adam_matches_torch_optim_adam(dtype, on_torch_ops, eps, monkeypatch) -> None:
    """The fused kernel (and the torch-ops path other devices take) against torch.optim.Adam, with a
    learning rate that changes between steps and a parameter whose gradient is missing on one step."""
    if on_torch_ops:  # the path CUDA tensors take, exercised on the CPU
        monkeypatch.setattr(optim, "_adam_kernel", lambda *args: pytest.fail("the kernel ran"))
        monkeypatch.setattr(torch.Tensor, "is_contiguous", lambda self, *args, **kwargs: False)
    generator = torch.Generator().manual_seed(0)
    start = [torch.randn(257, 3, generator=generator, dtype=dtype), torch.randn(11, generator=generator, dtype=dtype)]
    ours = [torch.nn.Parameter(value.clone()) for value in start]
    reference = [torch.nn.Parameter(value.clone()) for value in start]
    adam = Adam([{"params": ours, "lr": 0.01}], eps=eps)
    torch_adam = torch.optim.Adam([{"params": reference, "lr": 0.01}], eps=eps)
    for step in range(6):
        for group in adam.param_groups + torch_adam.param_groups:
            group["lr"] = 0.01 * 0.7**step
        grads = [torch.randn(value.shape, generator=generator, dtype=dtype) * 10.0 ** (step - 3) for value in start]
        for params in (ours, reference):
            for index, (param, grad) in enumerate(zip(params, grads)):
                param.grad = None if (step == 2 and index == 1) else grad.clone()
        adam.step()
        torch_adam.step()
    monkeypatch.undo()
    tolerance = 1e-6 if dtype == torch.float32 else 1e-12
    for param, expected, value in zip(ours, reference, start):
        assert (param - value).abs().max() > 1e-3  # it moved
        torch.testing.assert_close(param.detach(), expected.detach(), rtol=tolerance, atol=tolerance)
        torch.testing.assert_close(adam.state[param]["exp_avg_sq"], torch_adam.state[expected]["exp_avg_sq"], rtol=tolerance, atol=1e-30)
    assert adam.state[ours[1]]["step"] == 5 and adam.state[ours[0]]["step"] == 6
    adam.zero_grad()
    assert all(param.grad is None for param in ours)


@pytest.mark.parametrize("on_torch_ops", [False, True])
def test_row_scale_scales_each_rows_steps(on_torch_ops, monkeypatch) -> None:
    """Adam's moments do not depend on the parameter, so with per-row factors s every row moves s times as
    far as plain torch.optim.Adam moves it, over any number of steps (a factor 0 freezes the row)."""
    if on_torch_ops:
        monkeypatch.setattr(optim, "_adam_rows_kernel", lambda *args: pytest.fail("the kernel ran"))
        monkeypatch.setattr(torch.Tensor, "is_contiguous", lambda self, *args, **kwargs: False)
    generator = torch.Generator().manual_seed(1)
    start = torch.randn(40, 2, 3, generator=generator, dtype=torch.float64)
    scale = torch.linspace(0.0, 33.0, 40, dtype=torch.float64)
    ours, reference = torch.nn.Parameter(start.clone()), torch.nn.Parameter(start.clone())
    adam = Adam([{"params": [ours], "lr": 1e-3, "row_scale": scale}])
    torch_adam = torch.optim.Adam([reference], lr=1e-3, eps=ADAM_EPS)
    for _ in range(5):
        grad = torch.randn(start.shape, generator=generator, dtype=torch.float64)
        ours.grad, reference.grad = grad.clone(), grad.clone()
        adam.step()
        torch_adam.step()
    monkeypatch.undo()
    expected = start + scale[:, None, None] * (reference.detach() - start)
    torch.testing.assert_close(ours.detach(), expected, rtol=1e-12, atol=1e-12)
    assert torch.equal(ours.detach()[0], start[0]) and (ours.detach()[-1] - start[-1]).abs().min() > 1e-3


def test_row_scale_must_match_the_rows() -> None:
    param = torch.nn.Parameter(torch.zeros(5, 3))
    param.grad = torch.ones(5, 3)
    with pytest.raises(ValueError, match="5"):
        Adam([{"params": [param], "lr": 0.1, "row_scale": torch.ones(4)}]).step()


def test_create_optimizers_puts_row_scales_in_the_named_groups() -> None:
    params = {"means": torch.nn.Parameter(torch.zeros(3, 3)), "sh_dc": torch.nn.Parameter(torch.zeros(3, 1, 3))}
    optimizers = create_optimizers(params, LearningRates(), row_scales={"means": torch.tensor([0.0, 1.0, 10.0])})
    torch.testing.assert_close(optimizers["means"].param_groups[0]["row_scale"], torch.tensor([0.0, 1.0, 10.0]))
    assert "row_scale" not in optimizers["sh_dc"].param_groups[0]
    with pytest.raises(ValueError, match="colour"):
        create_optimizers(params, LearningRates(), row_scales={"colour": torch.ones(3)})
