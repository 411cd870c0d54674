"""Differentiable Gaussian rendering: one functional entry point, CPU (numba) and CUDA (gsplat)."""

from avatarperfect_cli.render.camera import Camera, look_at
from avatarperfect_cli.render.rasterization import RenderOutput, rasterization

__all__ = ["Camera", "RenderOutput", "look_at", "rasterization"]
