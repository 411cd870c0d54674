"""Per-frame body-pose refinement during training (GART): each video frame's pose corrected against its
pixels together with the avatar.

Each frame gets a learnable axis-angle offset (24, 3), the root's included, and a translation offset (3,).
A step that draws frame t moves only frame t's offsets, by Adam with frame t's own moments and step count:
a frame is drawn about once in `len(video)` steps, so one Adam over all frames would take its steps with
moments that other frames' gradients made, and (at GART's rate of 1e-4) a frame drawn 20 times would move
by at most 0.1°.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from avatarperfect_cli.devices import CPU
from avatarperfect_cli.training.optim import ADAM_BETAS

# Adam's denominator floor of the offsets (radians, metres): far below a gradient the images give.
_EPS = 1e-8


@dataclass
class PoseRefinementConfig:
    """learning_rate: Adam step of a frame's offsets per draw of that frame (radians, metres);
    start_step: first training step that uses and moves them (the Gaussians first learn the body)."""

    learning_rate: float = 3e-3
    start_step: int = 300


class PoseRefiner:
    """Learnable pose and translation offsets of `frames` video frames."""

    def __init__(
        self, frames: int, config: PoseRefinementConfig | None = None, device: torch.device = CPU
    ) -> None:
        self.config = config or PoseRefinementConfig()
        self.pose_offsets = torch.nn.Parameter(torch.zeros(frames, 24, 3, device=device))
        self.transl_offsets = torch.nn.Parameter(torch.zeros(frames, 3, device=device))
        self._exp_avg = torch.zeros(frames, 24 * 3 + 3, device=device)
        self._exp_avg_sq = torch.zeros(frames, 24 * 3 + 3, device=device)
        self._steps = [0] * frames

    def pose(self, frame: int, body_pose: torch.Tensor, transl: torch.Tensor, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Frame `frame`'s pose (24, 3) and translation (3,), offset once refinement has started."""
        if step < self.config.start_step:
            return body_pose, transl
        return body_pose + self.pose_offsets[frame], transl + self.transl_offsets[frame]

    @torch.no_grad()
    def step(self, frame: int, step: int) -> None:
        """Move frame `frame`'s offsets by their gradients (call after backward) and clear the gradients."""
        pose_grad, transl_grad = self.pose_offsets.grad, self.transl_offsets.grad
        self.pose_offsets.grad = self.transl_offsets.grad = None
        if step < self.config.start_step or pose_grad is None or transl_grad is None:
            return
        grad = torch.cat([pose_grad[frame].flatten(), transl_grad[frame]])
        beta1, beta2 = ADAM_BETAS
        self._steps[frame] += 1
        count = self._steps[frame]
        exp_avg, exp_avg_sq = self._exp_avg[frame], self._exp_avg_sq[frame]
        exp_avg.lerp_(grad, 1.0 - beta1)
        exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1.0 - beta2)
        denominator = (exp_avg_sq / (1.0 - beta2**count)).sqrt_().add_(_EPS)
        update = self.config.learning_rate / (1.0 - beta1**count) * exp_avg / denominator
        self.pose_offsets[frame] -= update[:72].reshape(24, 3)
        self.transl_offsets[frame] -= update[72:]

    def refined(self, body_pose: torch.Tensor, transl: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """All frames' refined poses (T, 24, 3) and translations (T, 3) given the original ones, on their device."""
        pose_offsets = self.pose_offsets.detach().to(body_pose.device)
        return body_pose + pose_offsets, transl + self.transl_offsets.detach().to(transl.device)
