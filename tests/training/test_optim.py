import math

import pytest
import torch

from avatarperfect_cli.training.optim import LearningRates, create_optimizers, exponential_decay, set_learning_rates


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
