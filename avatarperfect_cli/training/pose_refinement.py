"""Per-frame body-pose refinement for real videos, whose fitted SMPL poses are only approximate.

Each video frame gets a learnable axis-angle offset (24, 3) and translation offset (3,), optimised by
Adam together with the avatar from `start_step` on (GART: step 500, learning rate 1e-4). Synthetic
videos have exact poses and leave this off.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from avatarperfect_cli.devices import CPU
from avatarperfect_cli.training.optim import Adam


@dataclass
class PoseRefinementConfig:
    """learning_rate: Adam step size of the offsets (radians, metres); start_step: first step that uses them."""

    learning_rate: float = 1e-4
    start_step: int = 500


class PoseRefiner:
    """Learnable pose and translation offsets of `frames` video frames."""

    def __init__(
        self, frames: int, config: PoseRefinementConfig | None = None, device: torch.device = CPU
    ) -> None:
        self.config = config or PoseRefinementConfig()
        self.pose_offsets = torch.nn.Parameter(torch.zeros(frames, 24, 3, device=device))
        self.transl_offsets = torch.nn.Parameter(torch.zeros(frames, 3, device=device))
        self.optimizer = Adam([{"params": [self.pose_offsets, self.transl_offsets], "lr": self.config.learning_rate}])

    def pose(self, frame: int, body_pose: torch.Tensor, transl: torch.Tensor, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Frame `frame`'s pose (24, 3) and translation (3,), offset once refinement has started."""
        if step < self.config.start_step:
            return body_pose, transl
        return body_pose + self.pose_offsets[frame], transl + self.transl_offsets[frame]

    def step(self, step: int) -> None:
        """Apply and clear the offsets' gradients (call after backward)."""
        if step >= self.config.start_step:
            self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def refined(self, body_pose: torch.Tensor, transl: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """All frames' refined poses (T, 24, 3) and translations (T, 3) given the original ones, on their device."""
        pose_offsets = self.pose_offsets.detach().to(body_pose.device)
        return body_pose + pose_offsets, transl + self.transl_offsets.detach().to(transl.device)
