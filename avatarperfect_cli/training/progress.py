"""A rich progress bar for training: step, loss, PSNR of the current view, Gaussian count, speed."""

from __future__ import annotations

from types import TracebackType

import torch
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from avatarperfect_cli.training.metrics import psnr

REFRESH_EVERY = 10  # steps between statistics updates (PSNR is not free at 512²)


class TrainingProgress:
    """Context manager; `update` once per step. Disabled: does nothing (tests, --quiet)."""

    def __init__(self, total: int, enabled: bool = True, description: str = "training") -> None:
        self.enabled = enabled
        self.steps = 0
        self.progress = Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("loss {task.fields[loss]:.4f}  PSNR {task.fields[psnr]:5.2f} dB  {task.fields[count]:,} Gaussians"),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
            console=Console(stderr=True),
            disable=not enabled,
        )
        self.task = self.progress.add_task(description, total=total, loss=0.0, psnr=0.0, count=0)

    def __enter__(self) -> TrainingProgress:
        self.progress.__enter__()
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        self.progress.__exit__(kind, error, trace)

    def update(self, loss: float | torch.Tensor, image: torch.Tensor, target: torch.Tensor, count: int) -> None:
        """`loss` may be a 0-d tensor: it is read (a wait for the GPU) only on the steps that refresh."""
        self.steps += 1
        if self.enabled and (self.steps % REFRESH_EVERY == 0 or self.steps == 1):
            self.progress.update(self.task, advance=0, loss=float(loss), psnr=psnr(image, target), count=count)
        self.progress.advance(self.task)
