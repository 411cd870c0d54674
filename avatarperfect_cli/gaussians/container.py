"""The Gaussians container: parameters in the 3DGS PLY convention, as torch tensors."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import torch


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per colour channel for a degree 0..3."""
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be in 0..3, got {degree}")
    return (degree + 1) ** 2


def sh_degree_from_bases(bases: int) -> int:
    """Inverse of `num_sh_bases`; raises ValueError if `bases` is not 1, 4, 9 or 16."""
    degree = math.isqrt(bases) - 1
    if degree < 0 or degree > 3 or (degree + 1) ** 2 != bases:
        raise ValueError(f"{bases} SH coefficients per channel is not a degree 0..3 layout")
    return degree


@dataclass
class Gaussians:
    """N anisotropic 3D Gaussians, stored as optimisable (unconstrained) parameters.

    means:          (N, 3) metres, world (or canonical body) frame
    quats:          (N, 4) rotation quaternions w x y z; need not be normalised
    log_scales:     (N, 3) natural log of the standard deviations along the local axes, metres
    opacity_logits: (N,)   logit of the opacity in (0, 1)
    sh:             (N, K, 3) SH coefficients, K = (degree + 1)^2; sh[:, 0] is the DC term
    extras:         name -> (N, D) per-Gaussian attributes (e.g. skinning weights) kept by PLY I/O
    metadata:       JSON-serialisable dict kept by PLY I/O (body model, rest joints, ...)
    """

    means: torch.Tensor
    quats: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    sh: torch.Tensor
    extras: dict[str, torch.Tensor] = field(default_factory=dict)
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        expected = {
            "means": (n, 3),
            "quats": (n, 4),
            "log_scales": (n, 3),
            "opacity_logits": (n,),
        }
        for name, shape in expected.items():
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(f"{name} has shape {tuple(getattr(self, name).shape)}, expected {shape}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"sh has shape {tuple(self.sh.shape)}, expected ({n}, K, 3)")
        sh_degree_from_bases(self.sh.shape[1])
        for name, value in self.extras.items():
            if value.ndim != 2 or value.shape[0] != n:
                raise ValueError(f"extra '{name}' has shape {tuple(value.shape)}, expected ({n}, D)")

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_bases(self.sh.shape[1])

    @property
    def scales(self) -> torch.Tensor:
        """(N, 3) standard deviations, metres."""
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        """(N,) opacities in (0, 1)."""
        return torch.sigmoid(self.opacity_logits)

    @property
    def unit_quats(self) -> torch.Tensor:
        """(N, 4) normalised quaternions w x y z."""
        return torch.nn.functional.normalize(self.quats, dim=-1)

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Gaussians:
        def move(t: torch.Tensor) -> torch.Tensor:
            return t.to(device=device, dtype=dtype if t.is_floating_point() else None)

        return replace(
            self,
            means=move(self.means),
            quats=move(self.quats),
            log_scales=move(self.log_scales),
            opacity_logits=move(self.opacity_logits),
            sh=move(self.sh),
            extras={k: move(v) for k, v in self.extras.items()},
        )
