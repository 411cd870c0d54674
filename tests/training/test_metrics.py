import math

import torch

from avatarperfect_cli.training.metrics import iou, psnr, ssim


def test_psnr_of_a_constant_offset() -> None:
    target = torch.rand(16, 20, 3, generator=torch.Generator().manual_seed(0)) * 0.5
    assert math.isclose(psnr(target + 0.1, target), 20.0, rel_tol=1e-6)  # mse 0.01
    assert math.isclose(psnr(target + 0.01, target), 40.0, rel_tol=1e-6)
    assert psnr(target, target) == math.inf


def test_ssim_metric_on_constant_images() -> None:
    a, b, c1 = 0.25, 0.875, 0.01**2  # exact in float32
    x = torch.full((15, 18, 3), a)
    y = torch.full((15, 18, 3), b)
    assert math.isclose(ssim(x, y), (2 * a * b + c1) / (a * a + b * b + c1), rel_tol=1e-9)
    assert math.isclose(ssim(x, x), 1.0, rel_tol=1e-6)


def test_iou_of_overlapping_squares() -> None:
    first = torch.zeros(30, 30, dtype=torch.bool)
    second = torch.zeros(30, 30, dtype=torch.bool)
    first[0:10, 0:10] = True
    second[5:15, 5:15] = True
    assert math.isclose(iou(first, second), 25 / 175)
    assert iou(first, first) == 1.0
    assert iou(first, torch.zeros(30, 30)) == 0.0
    assert iou(torch.zeros(4, 4), torch.zeros(4, 4)) == 1.0
    assert math.isclose(iou(first.float(), second.to(torch.uint8)), 25 / 175)
