"""CPU-vs-CUDA parity of whole stages. Needs a CUDA GPU and gsplat; skipped otherwise.

- train-initial: the same 200-iteration fit on the CPU and on CUDA (the committed 256² sample at 128²)
  reaches a held-out PSNR within 0.3 dB. Both avatars are scored by the same CPU renderer, so the
  difference is the training's; the CUDA avatar is also scored on CUDA (the renderers agree to 0.1 dB).
- visibility: V of one avatar on both devices agrees (the CUDA backend's V is exact, not sampled).
- suggest: on both devices, from the same avatar, the suggested poses' objectives are within 5 %.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from avatarperfect_cli.datasets.people_snapshot import FrameRange
from avatarperfect_cli.io.workspace import open_workspace
from avatarperfect_cli.refinement.suggest import SuggestConfig
from avatarperfect_cli.stages.evaluate import evaluate
from avatarperfect_cli.stages.suggest import SuggestSettings, suggest
from avatarperfect_cli.stages.train_initial import InitialFit, VideoSettings, train_initial
from avatarperfect_cli.stages.visibility import visibility

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")

SAMPLE = Path(__file__).resolve().parents[2] / "examples" / "sample"
DEVICES = ("cpu", "cuda")
TEST_FRAMES = FrameRange(0, 19, 2)


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> dict[str, Path]:
    """One workspace per device, trained alike: 200 iterations on every 3rd frame at 128²."""
    pytest.importorskip("gsplat")
    roots = {}
    for device in DEVICES:
        root = tmp_path_factory.mktemp(f"parity-{device}") / "ws"
        fit = InitialFit(
            video=VideoSettings(frames=FrameRange(0, 59, 3), resolution=128), iterations=200, device=torch.device(device)
        )
        train_initial(SAMPLE / "train", root, fit, progress=False)
        roots[device] = root
    return roots


def held_out_psnr(root: Path, device: str) -> float:
    metrics = evaluate(root, SAMPLE / "test", frames=TEST_FRAMES, progress=False, device=torch.device(device))
    return metrics["mean"]["psnr"]


def test_train_initial_reaches_the_same_held_out_psnr(trained: dict[str, Path]):
    on_cpu = {device: held_out_psnr(root, "cpu") for device, root in trained.items()}
    cuda_on_cuda = held_out_psnr(trained["cuda"], "cuda")
    print(f"held-out PSNR: CPU-trained {on_cpu['cpu']:.3f} dB, CUDA-trained {on_cpu['cuda']:.3f} dB "
          f"(rendered on CUDA: {cuda_on_cuda:.3f} dB)")  # fmt: skip
    assert on_cpu["cpu"] > 15.0 and on_cpu["cuda"] > 15.0  # both fits learnt something
    assert abs(on_cpu["cpu"] - on_cpu["cuda"]) <= 0.3
    assert abs(cuda_on_cuda - on_cpu["cuda"]) <= 0.1


@pytest.fixture(scope="module")
def copies(trained: dict[str, Path], tmp_path_factory) -> dict[str, Path]:
    """Two copies of the CPU-trained workspace, one per device, each with V computed on its device."""
    roots = {}
    for device in DEVICES:
        root = tmp_path_factory.mktemp(f"suggest-{device}") / "ws"
        shutil.copytree(trained["cpu"], root)
        visibility(root, progress=False, device=torch.device(device))
        roots[device] = root
    return roots


def test_visibility_agrees(copies: dict[str, Path]):
    import numpy as np

    values = {}
    for device, root in copies.items():
        (path,) = sorted((root / "visibility").glob("*.npz"))
        with np.load(path) as data:
            values[device] = torch.from_numpy(data["visibility"]).double()
    scale = values["cpu"].abs().max()
    assert scale > 0
    assert (values["cuda"] - values["cpu"]).abs().max() <= 1e-2 * scale


def test_suggest_objectives_agree(copies: dict[str, Path]):
    search = SuggestConfig(starts=2, steps=20, candidates=16)
    objectives = {}
    for device, root in copies.items():
        folder = suggest(root, SuggestSettings(search=search, device=torch.device(device)), progress=False)
        objectives[device] = json.loads((folder / "suggestion.json").read_text())["objective"]
        assert open_workspace(root).iteration == 0
    print(f"suggest objectives: CPU {objectives['cpu']:.3f}, CUDA {objectives['cuda']:.3f}")
    assert objectives["cpu"] < 0 and objectives["cuda"] < 0  # both found barely-seen Gaussians to show
    assert abs(objectives["cuda"] - objectives["cpu"]) <= 0.05 * abs(objectives["cpu"])
