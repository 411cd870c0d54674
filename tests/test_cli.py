"""The command line as a user runs it: help, one-line errors, nothing written on failure."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from avatarperfect_cli.cli import app

PIPELINE_COMMANDS = ["train-initial", "visibility", "suggest", "render", "apply-edit", "refine", "evaluate"]


def test_help_lists_pipeline():
    result = subprocess.run([sys.executable, "-m", "avatarperfect_cli", "--help"], capture_output=True, text=True)
    assert result.returncode == 0
    for command in PIPELINE_COMMANDS:
        assert command in result.stdout


def test_help_does_not_import_heavy_modules():
    """--help stays fast (0.15 s measured, docs/performance.md) because torch and numba load lazily."""
    probe = "import sys; from avatarperfect_cli import cli; print('torch' in sys.modules, 'numba' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert result.stdout.split() == ["False", "False"]


def test_bad_ply_is_one_line_error_and_writes_nothing(tmp_path: Path):
    ply = tmp_path / "broken.ply"
    ply.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\nend_header\n\x00\x00")
    camera = tmp_path / "camera.json"
    camera.write_text('{"K": [[10,0,4],[0,10,4],[0,0,1]], "world_to_camera": [[1,0,0,0],[0,1,0,0],[0,0,1,2],[0,0,0,1]], "width": 8, "height": 8}')
    output = tmp_path / "out.png"
    result = CliRunner().invoke(app, ["render", str(ply), "--camera", str(camera), "-o", str(output)])
    assert result.exit_code == 2
    message = result.stderr.strip()
    assert len(message.splitlines()) == 1 and "broken.ply" in message and message.startswith("error:")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.ply", "camera.json"]


def test_render_writes_rgb_and_alpha(tmp_path: Path):
    from avatarperfect_cli.gaussians import Gaussians, rgb_to_sh
    from avatarperfect_cli.io import read_image, write_camera, write_gaussians
    from avatarperfect_cli.render import Camera

    n = 50
    generator = torch.Generator().manual_seed(0)
    gaussians = Gaussians(
        means=(torch.rand(n, 3, generator=generator) - 0.5) * 0.5,
        quats=torch.randn(n, 4, generator=generator),
        log_scales=torch.full((n, 3), -3.0),
        opacity_logits=torch.full((n,), 3.0),
        sh=rgb_to_sh(torch.tensor([1.0, 0.0, 0.0])).expand(n, 1, 3).clone(),
    )
    write_gaussians(tmp_path / "g.ply", gaussians)
    view = torch.eye(4)
    view[2, 3] = 2.0
    write_camera(tmp_path / "c.json", Camera(torch.tensor([[40.0, 0, 16], [0, 40, 12], [0, 0, 1]]), view, 32, 24))
    result = CliRunner().invoke(app, ["render", str(tmp_path / "g.ply"), "-c", str(tmp_path / "c.json"), "-o", str(tmp_path / "r.png")])
    assert result.exit_code == 0, result.output
    rgb = read_image(tmp_path / "r.png")
    alpha = read_image(tmp_path / "r_alpha.png", mode="L")
    assert rgb.shape == (24, 32, 3) and alpha.shape == (24, 32, 1)
    assert (alpha > 0.99).any() and (alpha == 0).any()
    # Red Gaussians composited over white: rgb = alpha * red + (1 - alpha) * white, to 8-bit rounding.
    expected = alpha * torch.tensor([1.0, 0.0, 0.0]) + (1 - alpha) * torch.ones(3)
    assert (rgb - expected).abs().max() <= 1.5 / 255


def test_bad_background_is_rejected(tmp_path: Path):
    result = CliRunner().invoke(app, ["render", "x.ply", "-c", "c.json", "-o", str(tmp_path / "o.png"), "--background", "mauve"])
    assert result.exit_code == 2 and "background" in result.stderr


@pytest.mark.parametrize(
    "arguments, problem",
    [
        (["train-initial", "{tmp}/data", "{tmp}/ws", "--iterations", "0"], "--iterations must be at least 1, got 0"),
        (["train-initial", "{tmp}/data", "{tmp}/ws", "--resolution", "1"], "--resolution must be at least 16, got 1"),
        (["train-initial", "{tmp}/data", "{tmp}/ws", "--sh-degree", "4"], "--sh-degree must be from 0 to 3, got 4"),
        (["train-initial", "{tmp}/data", "{tmp}/ws", "--max-gaussians", "0"], "--max-gaussians must be at least 1, got 0"),
        (["make-sample", "{tmp}/sample", "--resolution", "1"], "--resolution must be from 16 to 8192, got 1"),
        (["prepare", "{tmp}/v.mp4", "{tmp}/out", "--max-side", "8"], "--max-side (or 0: the video's size) must be at least 16, got 8"),
        (["prepare", "{tmp}/v.mp4", "{tmp}/out", "--every", "0"], "--every must be at least 1, got 0"),
        (["prepare", "{tmp}/v.mp4", "{tmp}/out", "--max-frames", "-1"], "--max-frames (or 0: no limit) must be at least 0, got -1"),
        (["make-sample", "{tmp}/sample", "--resolution", "30000"], "--resolution must be from 16 to 8192, got 30000"),
        (["suggest", "{tmp}/ws", "--exposure-poses", "-1"], "--exposure-poses must be at least 0, got -1"),
        (["train-initial", "{tmp}/data", "{tmp}/ws", "--body-shape", "guess"], "--body-shape 'guess' is not one of auto, fit, exact"),
        (["make-sample", "{tmp}/sample", "--body", "height=1.5"], "anny phenotype height=1.5 is outside [0, 1]"),
        (["make-sample", "{tmp}/sample", "--body", "stature=0.5"], "unknown anny phenotype stature; known: gender, age, muscle, weight, height, proportions"),
        (["make-sample", "{tmp}/sample", "--body", "height"], "--body 'height': 'height' is not NAME=VALUE with a number"),
    ],
)
def test_out_of_range_options_are_one_line(tmp_path: Path, arguments: list[str], problem: str):
    """Not typer's five-line usage box: one line, status 2, before any work (nothing is written)."""
    result = CliRunner().invoke(app, [argument.format(tmp=tmp_path) for argument in arguments])
    assert result.exit_code == 2
    assert result.stderr.strip() == f"error: {problem}"
    assert list(tmp_path.iterdir()) == []


def test_an_unwritable_workspace_path_is_refused_before_training(tmp_path: Path):
    (tmp_path / "file").write_text("")
    result = CliRunner().invoke(app, ["train-initial", str(tmp_path / "data"), str(tmp_path / "file" / "ws")])
    assert result.exit_code == 2
    assert result.stderr.strip() == f"error: {tmp_path / 'file' / 'ws'}: cannot be written: {tmp_path / 'file'} is not a folder"


@pytest.mark.parametrize("command", ["train-initial", "render"])
def test_device_cuda_without_a_gpu_is_one_line_and_writes_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, command: str
):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    sample = Path(__file__).resolve().parents[1] / "examples" / "sample" / "train"
    arguments = {
        "train-initial": [str(sample), str(tmp_path / "ws"), "--iterations", "1", "--resolution", "32"],
        "render": [str(tmp_path / "ws"), "--turntable", "2", "-o", str(tmp_path / "turn.mp4")],
    }[command]
    result = CliRunner().invoke(app, [command, *arguments, "--device", "cuda"])
    assert result.exit_code == 2
    assert result.stderr.strip() == "error: --device cuda: no CUDA GPU is visible to torch; use --device cpu or auto"
    assert list(tmp_path.iterdir()) == []


def test_an_unknown_device_is_one_line(tmp_path: Path):
    result = CliRunner().invoke(app, ["visibility", str(tmp_path), "--device", "tpu"])
    assert result.exit_code == 2
    assert result.stderr.strip() == "error: --device tpu: give auto, cpu or cuda"
