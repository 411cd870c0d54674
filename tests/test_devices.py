"""`--device`: resolve_device, without creating a tensor on a GPU (none is needed)."""

from __future__ import annotations

import pytest
import torch

from avatarperfect_cli.devices import resolve_device
from avatarperfect_cli.errors import AvatarPerfectError


@pytest.mark.parametrize("has_cuda, expected", [(False, "cpu"), (True, "cuda")])
def test_auto_picks_cuda_only_when_torch_sees_a_gpu(monkeypatch: pytest.MonkeyPatch, has_cuda: bool, expected: str):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: has_cuda)
    assert resolve_device("auto") == torch.device(expected)
    assert resolve_device("cpu") == torch.device("cpu")


def test_auto_is_the_cpu_on_a_machine_without_cuda():
    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA GPU")
    assert resolve_device("auto") == torch.device("cpu")


def test_cuda_is_given_when_torch_sees_a_gpu(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("cuda") == torch.device("cuda")


def test_cuda_without_a_gpu_is_one_line(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(AvatarPerfectError) as error:
        resolve_device("cuda")
    assert str(error.value) == "--device cuda: no CUDA GPU is visible to torch; use --device cpu or auto"


@pytest.mark.parametrize("name", ["gpu", "CUDA", "cuda:0", ""])
def test_other_names_are_one_line(name: str):
    with pytest.raises(AvatarPerfectError) as error:
        resolve_device(name)
    assert str(error.value) == f"--device {name}: give auto, cpu or cuda"
