"""The `avatarperfect` command line. Each command parses arguments and calls one library function.

Heavy modules (torch, numba) are imported inside the commands so that `--help` stays fast.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Callable, Optional, TypeVar

import typer

app = typer.Typer(
    help="Repair 3D Gaussian Splatting human avatars by painting 2D images.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

F = TypeVar("F", bound=Callable[..., object])


def _one_line_errors(command: F) -> F:
    """Print expected failures (AvatarPerfectError) as one line on stderr and exit with status 2."""

    @functools.wraps(command)
    def wrapper(*args: object, **kwargs: object) -> object:
        from avatarperfect_cli.errors import AvatarPerfectError

        try:
            return command(*args, **kwargs)
        except AvatarPerfectError as error:
            typer.echo(f"error: {error}", err=True)
            raise typer.Exit(2) from None
        except KeyboardInterrupt:
            typer.echo("interrupted: nothing was written", err=True)
            raise typer.Exit(130) from None

    return wrapper  # type: ignore[return-value]


def _not_implemented(name: str) -> None:
    typer.echo(f"error: '{name}' is not implemented yet", err=True)
    raise typer.Exit(1)


@app.command("render")
@_one_line_errors
def render(
    source: Path = typer.Argument(..., help="A Gaussian PLY file."),
    camera: Path = typer.Option(..., "--camera", "-c", help="Camera JSON: K, world_to_camera, width, height."),
    output: Path = typer.Option(..., "--output", "-o", help="Output PNG (RGB)."),
    alpha_output: Optional[Path] = typer.Option(None, "--alpha", help="Alpha PNG [default: OUTPUT with _alpha]."),
    background: str = typer.Option("white", help="Background: white, black or R,G,B in 0..1."),
    device: str = typer.Option("auto", help="auto, cpu or cuda."),
) -> None:
    """Render Gaussians to a PNG and an alpha PNG."""
    from avatarperfect_cli.stages.render import render_ply

    render_ply(source, camera, output, alpha_output, background, device)


@app.command("train-initial")
def train_initial() -> None:
    """Fit the first avatar from a monocular video."""
    _not_implemented("train-initial")


@app.command("visibility")
def visibility() -> None:
    """Accumulate per-Gaussian visibility over the video and past edits."""
    _not_implemented("visibility")


@app.command("suggest")
def suggest() -> None:
    """Suggest the next body pose and camera to edit, and render it."""
    _not_implemented("suggest")


@app.command("apply-edit")
def apply_edit() -> None:
    """Register a painted image: derive its mask and apply background deletions."""
    _not_implemented("apply-edit")


@app.command("refine")
def refine() -> None:
    """Re-optimise the avatar on the video plus every painted image."""
    _not_implemented("refine")


@app.command("evaluate")
def evaluate() -> None:
    """IoU, PSNR and SSIM on held-out poses."""
    _not_implemented("evaluate")
