"""Adam optimizers of the avatar's per-Gaussian parameters: one Adam per parameter, as gsplat does, so
that densification can edit each parameter and its moments on its own (`training.strategy`).

`Adam` is torch.optim.Adam's update (no weight decay, no AMSGrad) with the same `param_groups` and
`state` layout, computed by one fused numba kernel per parameter on the CPU and by torch ops elsewhere.
torch.optim itself costs a command 1 s at its first use (it imports torch._dynamo) and its CPU update
about 3 ms per training step on a 48k-Gaussian avatar.

Learning rates are GART's (DESIGN.md "Learning rates"); steps count from 0.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
import torch

# Adam settings of 3DGS and gsplat: a tiny eps, so small gradients still move parameters.
ADAM_EPS = 1e-15
ADAM_BETAS = (0.9, 0.999)


@numba.njit(inline="always")
def _adam_element(param, grad, exp_avg, exp_avg_sq, i, beta1, beta2, step_size, bias_correction2_sqrt, eps) -> None:
    """Adam's update of element i of flat arrays (torch's formulas and operation order)."""
    g = grad[i]
    m = exp_avg[i] + (1.0 - beta1) * (g - exp_avg[i])
    v = beta2 * exp_avg_sq[i] + (1.0 - beta2) * g * g
    exp_avg[i] = m
    exp_avg_sq[i] = v
    param[i] -= step_size * m / (math.sqrt(v) / bias_correction2_sqrt + eps)


@numba.njit(cache=True, parallel=True)
def _adam_kernel(param, grad, exp_avg, exp_avg_sq, beta1, beta2, step_size, bias_correction2_sqrt, eps) -> None:
    """One Adam step in place on flat arrays of one dtype."""
    for i in numba.prange(param.shape[0]):
        _adam_element(param, grad, exp_avg, exp_avg_sq, i, beta1, beta2, step_size, bias_correction2_sqrt, eps)


@numba.njit(cache=True, parallel=True)
def _adam_rows_kernel(param, grad, exp_avg, exp_avg_sq, row_scale, beta1, beta2, step_size, bias_correction2_sqrt, eps) -> None:
    """`_adam_kernel` with row r's step (elements r * row size ... of the flat arrays) scaled by row_scale[r]."""
    row_size = param.shape[0] // row_scale.shape[0]
    for r in numba.prange(row_scale.shape[0]):
        row_step = step_size * row_scale[r]
        for i in range(r * row_size, (r + 1) * row_size):
            _adam_element(param, grad, exp_avg, exp_avg_sq, i, beta1, beta2, row_step, bias_correction2_sqrt, eps)


def _flat(tensor: torch.Tensor) -> np.ndarray:
    """A flat numpy view sharing `tensor`'s memory (contiguous CPU tensors only)."""
    return tensor.detach().numpy().reshape(-1)


class Adam:
    """Adam over parameter groups: {"params": [tensors], "lr": float, ...any other keys}.

    A group may hold "row_scale": a (rows,) tensor that scales the learning rate of each row (first index)
    of its parameters, e.g. per Gaussian; densification keeps it in step with the rows (`training.strategy`).

    state[param] = {"step": int, "exp_avg": tensor, "exp_avg_sq": tensor}, created at its first step;
    densification may replace parameters in `param_groups` and rows of the moments (`training.strategy`).
    """

    def __init__(
        self, param_groups: Iterable[dict[str, Any]], betas: tuple[float, float] = ADAM_BETAS, eps: float = ADAM_EPS
    ) -> None:
        self.param_groups = [dict(group, params=list(group["params"])) for group in param_groups]
        self.betas, self.eps = betas, eps
        self.state: dict[torch.Tensor, dict[str, Any]] = {}

    @torch.no_grad()
    def step(self) -> None:
        """Update every parameter that has a gradient."""
        beta1, beta2 = self.betas
        for group in self.param_groups:
            for param in group["params"]:
                if param.grad is None:
                    continue
                state = self.state.get(param)
                if state is None:
                    state = self.state[param] = {
                        "step": 0, "exp_avg": torch.zeros_like(param), "exp_avg_sq": torch.zeros_like(param)
                    }  # fmt: skip
                state["step"] += 1
                step_size = group["lr"] / (1.0 - beta1 ** state["step"])
                bias_correction2_sqrt = math.sqrt(1.0 - beta2 ** state["step"])
                moments = state["exp_avg"], state["exp_avg_sq"]
                row_scale = group.get("row_scale")
                if row_scale is not None and (param.ndim == 0 or row_scale.shape != param.shape[:1]):
                    raise ValueError(f"row_scale has shape {tuple(row_scale.shape)}; the parameter has {tuple(param.shape[:1])} rows")
                if param.device.type == "cpu" and param.is_contiguous() and param.dtype in (torch.float32, torch.float64):
                    arrays = [_flat(tensor) for tensor in (param, param.grad.to(param.dtype).contiguous(), *moments)]
                    settings = (beta1, beta2, step_size, bias_correction2_sqrt, self.eps)
                    if row_scale is None:
                        _adam_kernel(*arrays, *settings)
                    else:
                        _adam_rows_kernel(*arrays, row_scale.to(param.dtype).contiguous().numpy(), *settings)
                else:
                    _adam_torch(param, param.grad, *moments, row_scale, beta1, beta2, step_size, bias_correction2_sqrt, self.eps)

    def zero_grad(self, set_to_none: bool = True) -> None:
        """Drop (or zero) every parameter's gradient."""
        for group in self.param_groups:
            for param in group["params"]:
                if param.grad is not None:
                    if set_to_none:
                        param.grad = None
                    else:
                        param.grad.zero_()


def _adam_torch(param, grad, exp_avg, exp_avg_sq, row_scale, beta1, beta2, step_size, bias_correction2_sqrt, eps) -> None:
    """`_adam_kernel` as torch ops, for tensors on any device (row_scale: (rows,) or None)."""
    exp_avg.lerp_(grad, 1.0 - beta1)
    exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1.0 - beta2)
    step = exp_avg if row_scale is None else exp_avg * row_scale.to(param).reshape((-1,) + (1,) * (param.ndim - 1))
    param.addcdiv_(step, (exp_avg_sq.sqrt() / bias_correction2_sqrt).add_(eps), value=-step_size)


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
    params: Mapping[str, torch.nn.Parameter], rates: LearningRates, step: int = 0,
    row_scales: Mapping[str, torch.Tensor] | None = None,
) -> dict[str, Adam]:
    """One Adam (a single param group holding a single parameter) per named parameter, at `step`'s rates;
    row_scales: optional (N,) factors on the rates of named parameters, per row (Gaussian)."""
    row_scales = row_scales or {}
    unknown = set(row_scales) - set(params)
    if unknown:
        raise ValueError(f"row scales for unknown parameters {sorted(unknown)}")
    optimizers = {}
    for name, param in params.items():
        group = {"params": [param], "lr": rates.at(name, step), "name": name}
        if name in row_scales:
            group["row_scale"] = row_scales[name].detach().to(param.device)
        optimizers[name] = Adam([group])
    return optimizers


def set_learning_rates(optimizers: Mapping[str, Adam], rates: LearningRates, step: int) -> None:
    """Apply the schedules: call once per step before `optimizer.step()`."""
    for name, optimizer in optimizers.items():
        for group in optimizer.param_groups:
            group["lr"] = rates.at(name, step)
