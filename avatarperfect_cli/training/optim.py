"""Adam optimizers of the avatar's per-Gaussian parameters: one Adam per parameter, as gsplat does, so
that densification can edit each parameter and its moments on its own (`training.strategy`).

Learning rates are GART's (DESIGN.md "Learning rates"); steps count from 0.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import torch

# Adam settings of 3DGS and gsplat: a tiny eps, so small gradients still move parameters.
ADAM_EPS = 1e-15


def exponential_decay(step: int, start_step: int, stop_step: int, initial: float, final: float) -> float:
    """Log-linear interpolation from `initial` at `start_step` to `final` at `stop_step`, held outside."""
    if stop_step <= start_step:
        return final if step >= start_step else initial
    t = min(max((step - start_step) / (stop_step - start_step), 0.0), 1.0)
    return math.exp((1.0 - t) * math.log(initial) + t * math.log(final))


@dataclass
class LearningRates:
    """Adam learning rates per `Avatar` parameter name, and their schedules.

    means:        decays exponentially from `means` to `means_final` over [0, total_steps]
                  (metres; the avatar's canonical frame is not rescaled as 3DGS's scene extent is)
    skin_logits:  0 (frozen) before `skin_start`, then decays from `skin_logits` to
                  `skin_logits_final` over [skin_start, total_steps]
    the others:   constant
    """

    total_steps: int = 2000
    means: float = 1.6e-4
    means_final: float = 1.6e-6
    quats: float = 5e-3
    log_scales: float = 5e-3
    opacity_logits: float = 0.05
    sh_dc: float = 5e-3
    sh_rest: float = 2.5e-4
    skin_logits: float = 1e-4
    skin_logits_final: float = 1e-5
    skin_start: int = 500

    def at(self, name: str, step: int) -> float:
        """The learning rate of parameter `name` at `step`."""
        if name == "means":
            return exponential_decay(step, 0, self.total_steps, self.means, self.means_final)
        if name == "skin_logits":
            if step < self.skin_start:
                return 0.0
            return exponential_decay(step, self.skin_start, self.total_steps, self.skin_logits, self.skin_logits_final)
        if name in ("quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
            return getattr(self, name)
        raise ValueError(f"no learning rate for parameter '{name}'")


def create_optimizers(
    params: Mapping[str, torch.nn.Parameter], rates: LearningRates, step: int = 0
) -> dict[str, torch.optim.Adam]:
    """One Adam (a single param group holding a single parameter) per named parameter, at `step`'s rates;
    on CUDA the fused implementation (one kernel per step instead of a dozen)."""
    return {
        name: torch.optim.Adam(
            [{"params": [param], "lr": rates.at(name, step), "name": name}], eps=ADAM_EPS,
            fused=True if param.device.type == "cuda" else None,
        )  # fmt: skip
        for name, param in params.items()
    }


def set_learning_rates(optimizers: Mapping[str, torch.optim.Optimizer], rates: LearningRates, step: int) -> None:
    """Apply the schedules: call once per step before `optimizer.step()`."""
    for name, optimizer in optimizers.items():
        for group in optimizer.param_groups:
            group["lr"] = rates.at(name, step)
