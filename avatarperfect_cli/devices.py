"""The `--device` option: which torch device the avatar, its training views and its renders live on."""

from __future__ import annotations

import torch

from avatarperfect_cli.errors import AvatarPerfectError

DEVICE_NAMES = ("auto", "cpu", "cuda")
CPU = torch.device("cpu")


def resolve_device(name: str) -> torch.device:
    """'auto' (cuda when torch sees a CUDA GPU, else cpu), 'cpu' or 'cuda' -> a torch device.

    A one-line AvatarPerfectError for 'cuda' without a visible GPU and for any other name.
    """
    if name not in DEVICE_NAMES:
        raise AvatarPerfectError(f"--device {name}: give auto, cpu or cuda")
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise AvatarPerfectError("--device cuda: no CUDA GPU is visible to torch; use --device cpu or auto")
    return torch.device(name)
