"""The `render` stage: Gaussians + camera -> PNG images."""

from __future__ import annotations

from pathlib import Path

import torch

from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.gaussians import Gaussians
from avatarperfect_cli.io import read_camera, read_gaussians, write_image
from avatarperfect_cli.render import Camera, RenderOutput, rasterization

NAMED_BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


def parse_background(text: str) -> torch.Tensor:
    """'white', 'black' or 'R,G,B' with components in [0, 1] -> (3,) tensor."""
    if text in NAMED_BACKGROUNDS:
        return torch.tensor(NAMED_BACKGROUNDS[text])
    try:
        values = [float(part) for part in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not all(0.0 <= v <= 1.0 for v in values):
        raise AvatarPerfectError(f"background '{text}' is not white, black or R,G,B with values in 0..1")
    return torch.tensor(values)


def resolve_device(name: str) -> torch.device:
    """'auto' (CUDA when available), 'cpu' or 'cuda' -> a torch device."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name not in ("cpu", "cuda"):
        raise AvatarPerfectError(f"device '{name}' is not auto, cpu or cuda")
    if name == "cuda" and not torch.cuda.is_available():
        raise AvatarPerfectError("device 'cuda' was asked for but no CUDA GPU is available")
    return torch.device(name)


def render_gaussians(
    gaussians: Gaussians, camera: Camera, background: torch.Tensor, device: torch.device
) -> RenderOutput:
    """Render static Gaussians (their own SH degree) into one camera, without gradients."""
    gaussians = gaussians.to(device)
    with torch.no_grad():
        return rasterization(
            gaussians.means, gaussians.unit_quats, gaussians.scales, gaussians.opacities, gaussians.sh,
            camera.to(device=device), sh_degree=gaussians.sh_degree, background=background.to(device),
        )  # fmt: skip


def default_alpha_path(output: Path) -> Path:
    return output.with_name(f"{output.stem}_alpha.png")


def render_ply(
    source: Path,
    camera_path: Path,
    output: Path,
    alpha_output: Path | None = None,
    background: str = "white",
    device: str = "auto",
) -> None:
    """Render a Gaussian PLY with a camera JSON to an RGB PNG and an alpha PNG (both written atomically)."""
    if output.suffix.lower() != ".png":
        raise AvatarPerfectError(f"{output}: the output must be a .png file")
    gaussians = read_gaussians(source)
    camera = read_camera(camera_path)
    out = render_gaussians(gaussians, camera, parse_background(background), resolve_device(device))
    write_image(output, out.image.clamp(0, 1).cpu())
    write_image(alpha_output or default_alpha_path(output), out.alpha.cpu())
