"""Densify and prune (3DGS adaptive density control) as a strategy object, in the style of gsplat's
`DefaultStrategy`, so the training loop keeps no bookkeeping:

    strategy = DensifyStrategy(DensifyConfig())
    state = strategy.initialize_state()
    for step in range(steps):
        out = rasterization(...)
        strategy.step_pre_backward(params, optimizers, state, step, out)
        loss.backward()
        for optimizer in optimizers.values(): optimizer.step(); optimizer.zero_grad()
        strategy.step_post_backward(params, optimizers, state, step, out)   # may replace params

(post-backward only reads the retained means2d gradient, so it may also run before the optimizer steps.)

`params` maps names to per-Gaussian `torch.nn.Parameter`s (first dimension N); it must hold
"means" (N, 3) metres, "quats" (N, 4) w x y z, "log_scales" (N, 3) and "opacity_logits" (N,), and
may hold any others (SH, skinning logits...), which are copied along. `optimizers` maps the same
names to optimizers with that one parameter (`training.optim.create_optimizers`). Densification
replaces the entries of `params` and the parameters inside the optimizers, so read parameters
through `params` after each step.

The gradient statistic. The rasterizer's `means2d` are pixel positions; like gsplat, its gradient is
scaled by (W/2, H/2), i.e. taken w.r.t. normalised device coordinates, which is the screen-space
gradient of the reference 3DGS code that GART's threshold (1e-4) was tuned on. Our loss is GART's (mean
over the subject box of L1 + 0.1 (1 - SSIM)), so the threshold is kept as is (a measured Gaussian count
on real data is the check). The statistic is the mean of that gradient's norm over the steps in which
the Gaussian was drawn.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, MutableMapping
from dataclasses import dataclass

import torch

from avatarperfect_cli.body import quaternion_to_matrix
from avatarperfect_cli.render import RenderOutput
from avatarperfect_cli.training.optim import Adam

REQUIRED_PARAMETERS = ("means", "quats", "log_scales", "opacity_logits")


@dataclass
class DensifyConfig:
    """When and how to densify and prune. Steps count from 0; defaults are GART's.

    Refinement runs at refine_start, refine_start + refine_every, ... while < refine_stop
    (GART: 101, 302, 503, 704).
    grad_threshold:      mean normalised screen-gradient norm above which a Gaussian is grown
    clone_max_scale:     metres; a grown Gaussian whose largest standard deviation is at most this is
                         cloned (copied), a larger one is split in two
    split_factor:        a split's children have the parent's scales divided by this
    prune_opacity:       Gaussians with opacity below this are removed at each refinement
    max_gaussians:       growth stops at this count (the highest gradients grow first). The 512² samples
                         grow to about 52k; capped at 30k their initial avatars score the same held out and
                         train-initial takes a quarter less time, but the loop's five rounds gained less
                         (docs/performance.md)
    reset_opacity_every: every this many steps (0: never) opacities are clamped to
                         2 * prune_opacity, as in 3DGS; off by default (DESIGN.md lists no reset)
    max_scale:           metres (0: no bound); after every step, at every step of the run (not only while
                         densifying), no standard deviation exceeds this
    max_anisotropy:      (0: no bound) likewise, no Gaussian's largest standard deviation exceeds this many
                         times its second largest: needles are bounded, flat discs (the surface) are not
    Both bounds keep the streaks away (Gaussians stretched along a limb that show as spikes in new poses;
    docs/avatar-quality.md).
    """

    refine_start: int = 101
    refine_stop: int = 800
    refine_every: int = 201
    grad_threshold: float = 1e-4
    clone_max_scale: float = 0.005
    split_factor: float = 1.6
    prune_opacity: float = 0.1
    max_gaussians: int = 60_000
    reset_opacity_every: int = 0
    max_scale: float = 0.025
    max_anisotropy: float = 10.0


@dataclass
class DensifyState:
    """Gradient statistics since the last refinement; None until the first accumulation.

    grad_norm_sum:  (N,) sum of the normalised screen-gradient norms over the steps a Gaussian was drawn
    visible_count:  (N,) number of those steps
    """

    grad_norm_sum: torch.Tensor | None = None
    visible_count: torch.Tensor | None = None


@dataclass
class RefineStats:
    """What one refinement did; `total` is the Gaussian count after it."""

    cloned: int
    split: int
    pruned: int
    total: int


def replace_rows(
    params: MutableMapping[str, torch.nn.Parameter],
    optimizers: MutableMapping[str, Adam],
    keep: torch.Tensor,
    new_rows: dict[str, torch.Tensor],
) -> None:
    """Keep the rows `keep` (N,) bool of every parameter and append `new_rows[name]` (M, ...) to it.

    Each parameter is replaced by a new `torch.nn.Parameter` in `params` and in its optimizer; the
    optimizer's per-element state (Adam's moments) keeps the kept rows and is zero for the new ones, and
    a group's per-row rate factors ("row_scale") keep the kept rows and are 1 for the new ones.
    """
    for name, param in list(params.items()):
        appended = new_rows[name].to(param.dtype)
        new_param = torch.nn.Parameter(torch.cat([param.detach()[keep], appended]), requires_grad=param.requires_grad)
        optimizer = optimizers.get(name)
        if optimizer is not None:
            for group in optimizer.param_groups:
                if any(p is param for p in group["params"]) and group.get("row_scale") is not None:
                    row_scale = group["row_scale"]
                    group["row_scale"] = torch.cat([row_scale[keep], row_scale.new_ones(appended.shape[0])])
                group["params"] = [new_param if p is param else p for p in group["params"]]
            state = optimizer.state.pop(param, None)
            if state is not None:
                for key, value in state.items():
                    if isinstance(value, torch.Tensor) and value.shape == param.shape:
                        state[key] = torch.cat([value[keep], value.new_zeros((appended.shape[0],) + value.shape[1:])])
                optimizer.state[new_param] = state
        params[name] = new_param


@torch.no_grad()
def split_children(
    params: Mapping[str, torch.Tensor], split: torch.Tensor, split_factor: float, generator: torch.Generator
) -> dict[str, torch.Tensor]:
    """The two children of every Gaussian where `split` (N,) bool is set, as rows (2S, ...) per parameter
    (all first children, then all second): each a copy of its parent, centred at a sample of the parent
    Gaussian (means metres) and with its scales divided by `split_factor` (3DGS's split)."""
    children = {name: torch.cat([param[split], param[split]]) for name, param in params.items()}
    parents = params["means"][split]
    scales = torch.exp(params["log_scales"][split])
    offsets = torch.randn((2,) + parents.shape, generator=generator).to(parents)
    local_offsets = offsets * scales  # (2, S, 3) samples of each parent Gaussian in its local frame
    rotations = quaternion_to_matrix(params["quats"][split])
    children["means"] = (parents + torch.einsum("sij,csj->csi", rotations, local_offsets)).reshape(-1, 3)
    children["log_scales"] = children["log_scales"] - math.log(split_factor)
    return children


@torch.no_grad()
def bound_scales(log_scales: torch.Tensor, max_scale: float, max_anisotropy: float) -> None:
    """Clamp (N, 3) log standard deviations in place: each at most log(max_scale), and the largest at most
    log(max_anisotropy) above the second largest (a bound of 0 is no bound)."""
    if max_anisotropy > 0:
        a, b, c = log_scales.unbind(dim=-1)
        # the second largest of three, exactly (median's sort costs 20 times more)
        second = torch.maximum(torch.minimum(a, b), torch.minimum(torch.maximum(a, b), c))
        log_scales.copy_(torch.minimum(log_scales, (second + math.log(max_anisotropy))[:, None]))
    if max_scale > 0:
        log_scales.clamp_(max=math.log(max_scale))


class DensifyStrategy:
    """Adaptive density control: clone small and split large Gaussians with large screen-space
    gradients, prune transparent ones; see the module docstring for the calling protocol."""

    def __init__(self, config: DensifyConfig | None = None, seed: int = 0) -> None:
        self.config = config or DensifyConfig()
        self._generator = torch.Generator().manual_seed(seed)

    def initialize_state(self) -> DensifyState:
        return DensifyState()

    def is_refine_step(self, step: int) -> bool:
        c = self.config
        return c.refine_start <= step < c.refine_stop and (step - c.refine_start) % c.refine_every == 0

    def step_pre_backward(
        self,
        params: MutableMapping[str, torch.nn.Parameter],
        optimizers: MutableMapping[str, Adam],
        state: DensifyState,
        step: int,
        render_output: RenderOutput,
    ) -> None:
        """Ask autograd to keep the gradient of the screen-space means (call before backward)."""
        if step < self.config.refine_stop:
            render_output.means2d.retain_grad()

    def step_post_backward(
        self,
        params: MutableMapping[str, torch.nn.Parameter],
        optimizers: MutableMapping[str, Adam],
        state: DensifyState,
        step: int,
        render_output: RenderOutput,
    ) -> RefineStats | None:
        """Bound the scales; accumulate the gradient statistic; at refine steps densify and prune (returns
        what it did)."""
        c = self.config
        bound_scales(params["log_scales"], c.max_scale, c.max_anisotropy)
        if step >= c.refine_stop:
            return None
        self._accumulate(state, render_output)
        stats = None
        if self.is_refine_step(step):
            stats = self._refine(params, optimizers, state)
        if c.reset_opacity_every > 0 and step > 0 and step % c.reset_opacity_every == 0:
            self._reset_opacities(params, optimizers)
        return stats

    @torch.no_grad()
    def _accumulate(self, state: DensifyState, render_output: RenderOutput) -> None:
        means2d = render_output.means2d
        if not (means2d.is_leaf or means2d.retains_grad) or means2d.grad is None:
            raise RuntimeError("means2d has no gradient: call step_pre_backward before backward")
        grad = means2d.grad
        n = grad.shape[0]
        if state.grad_norm_sum is None or state.grad_norm_sum.shape[0] != n:
            state.grad_norm_sum = grad.new_zeros(n)
            state.visible_count = grad.new_zeros(n)
        ndc_scale = grad.new_tensor([render_output.width / 2.0, render_output.height / 2.0])
        norms = (grad * ndc_scale).norm(dim=-1)
        # masks rather than boolean indexing: indexing waits for the GPU to count the selected rows
        visible = render_output.radii > 0
        state.grad_norm_sum += torch.where(visible, norms, 0.0)
        state.visible_count += visible

    @torch.no_grad()
    def _refine(
        self,
        params: MutableMapping[str, torch.nn.Parameter],
        optimizers: MutableMapping[str, Adam],
        state: DensifyState,
    ) -> RefineStats:
        c = self.config
        missing = [name for name in REQUIRED_PARAMETERS if name not in params]
        if missing:
            raise KeyError(f"densification needs the parameters {missing}")
        n = params["means"].shape[0]
        if state.grad_norm_sum is None or state.grad_norm_sum.shape[0] != n:
            raise RuntimeError(f"gradient statistics cover a different number of Gaussians than the {n} given")
        mean_grad = state.grad_norm_sum / state.visible_count.clamp_min(1)
        prune = torch.sigmoid(params["opacity_logits"]) < c.prune_opacity
        grow = (mean_grad > c.grad_threshold) & ~prune
        budget = max(c.max_gaussians - (n - int(prune.sum())), 0)
        if int(grow.sum()) > budget:
            ranked = torch.where(grow, mean_grad, torch.full_like(mean_grad, -1.0))
            grow = torch.zeros_like(grow)
            grow[torch.topk(ranked, budget).indices] = True
        log_scales = params["log_scales"]
        clone = grow & (log_scales.amax(dim=-1) <= math.log(c.clone_max_scale))
        split = grow & ~clone

        children = split_children(params, split, c.split_factor, self._generator)
        new_rows = {name: torch.cat([param[clone], children[name]]) for name, param in params.items()}
        clone_count = int(clone.sum())

        replace_rows(params, optimizers, ~prune & ~split, new_rows)
        state.grad_norm_sum = None
        state.visible_count = None
        return RefineStats(clone_count, int(split.sum()), int(prune.sum()), params["means"].shape[0])

    @torch.no_grad()
    def _reset_opacities(
        self, params: MutableMapping[str, torch.nn.Parameter], optimizers: MutableMapping[str, Adam]
    ) -> None:
        """Clamp opacities to 2 * prune_opacity and zero their optimizer moments."""
        value = 2.0 * self.config.prune_opacity
        param = params["opacity_logits"]
        param.clamp_(max=math.log(value / (1.0 - value)))
        optimizer = optimizers.get("opacity_logits")
        if optimizer is not None:
            for key, moment in optimizer.state.get(param, {}).items():
                if isinstance(moment, torch.Tensor) and moment.shape == param.shape:
                    moment.zero_()
