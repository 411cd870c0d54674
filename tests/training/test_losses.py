import math

import pytest
import torch

from avatarperfect_cli.training.losses import _ssim_conv, band_pixels, boundary_band, image_loss, l1_loss, mask_band_supervision, ssim, subject_bbox


def dense_ssim(x: torch.Tensor, y: torch.Tensor, border: int) -> torch.Tensor:
    """Mean SSIM in float64 straight from the definition: an 11x11 Gaussian window (sigma 1.5) slid
    over zero-padded (H, W, C) images, one window offset at a time."""
    x, y = x.double(), y.double()
    height, width, _ = x.shape
    offsets = torch.arange(11, dtype=torch.float64) - 5
    window = torch.exp(-(offsets[:, None] ** 2 + offsets[None, :] ** 2) / (2 * 1.5**2))
    window = window / window.sum()
    padded = [torch.nn.functional.pad(t.permute(2, 0, 1), (5, 5, 5, 5)) for t in (x, y, x * x, y * y, x * y)]
    moments = [torch.zeros(x.shape[2], height, width, dtype=torch.float64) for _ in range(5)]
    for dy in range(11):
        for dx in range(11):
            for moment, source in zip(moments, padded):
                moment += window[dy, dx] * source[:, dy : dy + height, dx : dx + width]
    mx, my, exx, eyy, exy = moments
    c1, c2 = 0.01**2, 0.03**2
    var_x, var_y, cov = exx - mx**2, eyy - my**2, exy - mx * my
    ssim_map = (2 * mx * my + c1) * (2 * cov + c2) / ((mx**2 + my**2 + c1) * (var_x + var_y + c2))
    if border:
        ssim_map = ssim_map[:, border:-border, border:-border]
    return ssim_map.mean()


def image_pair(height: int, width: int, channels: int, dtype: torch.dtype = torch.float32, seed: int = 0):
    generator = torch.Generator().manual_seed(seed)
    x = torch.rand(height, width, channels, generator=generator, dtype=dtype)
    # a correlated target so SSIM is far from 0 and 1
    y = (0.6 * x + 0.4 * torch.rand(height, width, channels, generator=generator, dtype=dtype)).clamp(0, 1)
    return x, y


@pytest.mark.parametrize("padding,border", [("same", 0), ("valid", 5)])
@pytest.mark.parametrize("shape", [(37, 29, 3), (16, 23, 1), (12, 11, 2)])
def test_ssim_matches_dense_reference(padding: str, border: int, shape: tuple[int, int, int]) -> None:
    x, y = image_pair(*shape, dtype=torch.float64)
    reference = dense_ssim(x, y, border)
    assert 0.2 < float(reference) < 0.95
    torch.testing.assert_close(ssim(x, y, padding), reference, rtol=0, atol=1e-12)
    torch.testing.assert_close(ssim(x.float(), y.float(), padding).double(), reference, rtol=0, atol=1e-5)
    torch.testing.assert_close(_ssim_conv(x, y, border), reference, rtol=0, atol=1e-12)


def test_ssim_of_constant_images_is_analytic() -> None:
    a, b = 0.2, 0.7
    x = torch.full((20, 24, 3), a, dtype=torch.float64)
    y = torch.full((20, 24, 3), b, dtype=torch.float64)
    c1 = 0.01**2
    expected = (2 * a * b + c1) / (a * a + b * b + c1)  # no variance inside the image: contrast term is 1
    assert math.isclose(float(ssim(x, y, "valid")), expected, rel_tol=1e-12)


@pytest.mark.parametrize("padding", ["same", "valid"])
def test_ssim_of_an_image_with_itself_is_one(padding: str) -> None:
    x, _ = image_pair(64, 48, 3)
    assert math.isclose(float(ssim(x, x, padding)), 1.0, abs_tol=1e-6)


@pytest.mark.parametrize("padding", ["same", "valid"])
def test_ssim_gradcheck(padding: str) -> None:
    x, y = image_pair(12, 11, 1, dtype=torch.float64, seed=1)
    x.requires_grad_()
    assert torch.autograd.gradcheck(lambda p: ssim(p, y, padding), (x,))
    y.requires_grad_()
    assert torch.autograd.gradcheck(lambda p, t: ssim(p, t, padding), (x, y))


def test_ssim_float32_gradient_matches_autograd_of_the_dense_reference() -> None:
    x, y = image_pair(40, 33, 3)
    x.requires_grad_()
    ssim(x, y).backward()
    x64 = x.detach().double().requires_grad_()
    dense_ssim(x64, y, 0).backward()
    torch.testing.assert_close(x.grad.double(), x64.grad, rtol=1e-3, atol=1e-8)


def test_ssim_rejects_bad_shapes() -> None:
    x, y = image_pair(8, 8, 3)
    with pytest.raises(ValueError):
        ssim(x, y[:, :4])
    with pytest.raises(ValueError):
        ssim(x, y, "valid")  # 8 px is smaller than the 11 px window


def test_image_loss_combines_l1_and_ssim() -> None:
    x, y = image_pair(30, 30, 3)
    assert float(image_loss(x, x)) == pytest.approx(0.0, abs=1e-6)
    expected = float((x - y).abs().mean()) + 0.1 * (1 - float(dense_ssim(x, y, 0)))
    assert float(image_loss(x, y)) == pytest.approx(expected, rel=1e-5)
    assert float(l1_loss(x, x + 0.25)) == pytest.approx(0.25)


def test_masked_image_loss_ignores_pixels_outside_the_mask() -> None:
    x, y = image_pair(30, 30, 3)
    mask = torch.zeros(30, 30, dtype=torch.bool)
    mask[5:15, 8:20] = True
    outside_only = torch.where(mask[..., None], x, y)
    assert float(image_loss(outside_only, x, mask)) == pytest.approx(0.0, abs=1e-6)
    inside_only = torch.where(mask[..., None], y, x)
    assert float(image_loss(inside_only, x, mask)) > 0.01


def test_subject_bbox() -> None:
    mask = torch.zeros(100, 120, dtype=torch.bool)
    mask[30:41, 50:61] = True
    mask[35, 70] = True
    assert subject_bbox(mask, margin=20) == (slice(10, 61), slice(30, 91))
    assert subject_bbox(mask, margin=0) == (slice(30, 41), slice(50, 71))
    corner = torch.zeros(100, 120)
    corner[2, 115] = 1.0
    assert subject_bbox(corner, margin=20) == (slice(0, 23), slice(95, 120))
    assert subject_bbox(torch.zeros(5, 7), margin=3) == (slice(0, 5), slice(0, 7))


@pytest.mark.parametrize("padding,border", [("same", 0), ("valid", 5)])
@pytest.mark.parametrize("dtype, tolerance", [(torch.float32, 1e-5), (torch.float64, 1e-12)])
def test_torch_ssim_matches_the_numba_kernel_forward_and_backward(
    padding: str, border: int, dtype: torch.dtype, tolerance: float
) -> None:
    """The conv2d SSIM that non-CPU tensors take (CUDA training and evaluation) against the numba kernel the
    CPU takes: the value and the gradients of both images."""
    x, y = image_pair(45, 38, 3, dtype=dtype, seed=2)
    upstream = 0.7  # a non-unit incoming gradient, as in the loss 0.1 * (1 - SSIM)
    results = []
    for function in (lambda p, t: ssim(p, t, padding), lambda p, t: _ssim_conv(p, t, border)):
        pred, target = x.clone().requires_grad_(), y.clone().requires_grad_()
        value = function(pred, target)
        (value * upstream).backward()
        results.append((value.detach(), pred.grad, target.grad))
    (numba_value, numba_pred, numba_target), (conv_value, conv_pred, conv_target) = results
    assert 0.2 < float(numba_value) < 0.95
    torch.testing.assert_close(conv_value, numba_value, rtol=0, atol=tolerance)
    scale = float(numba_pred.abs().max())
    assert scale > 0
    torch.testing.assert_close(conv_pred, numba_pred, rtol=0, atol=tolerance * scale)
    torch.testing.assert_close(conv_target, numba_target, rtol=0, atol=tolerance * scale)


def square_mask(size: int, low: int, high: int) -> torch.Tensor:
    mask = torch.zeros(size, size, dtype=torch.bool)
    mask[low:high, low:high] = True
    return mask


def test_boundary_band_marks_width_pixels_either_side_of_the_edge() -> None:
    band = boundary_band(square_mask(20, 6, 14), width=2)
    torch.testing.assert_close(band, square_mask(20, 4, 16) & ~square_mask(20, 8, 12))
    edge = torch.zeros(20, 20, dtype=torch.bool)
    edge[:, :5] = True  # the image border is no edge
    expected = torch.zeros(20, 20, dtype=torch.bool)
    expected[:, 3:7] = True
    torch.testing.assert_close(boundary_band(edge, width=2), expected)


def test_mask_band_supervision_lets_the_frame_decide_at_the_edge_of_a_dilated_mask() -> None:
    # The subject is the square 8..16 in a frame on white; the render is exactly it (opaque inside, empty
    # outside) over a random background. Against a mask dilated by 2 px the plain loss is large at the ring of
    # white the mask calls subject; with the band it is zero: no Gaussian is asked to grow into the ring.
    size, background = 24, torch.tensor([0.2, 0.5, 0.9])
    subject = square_mask(size, 8, 16)
    colour = torch.tensor([0.7, 0.1, 0.3])
    alpha = subject.float()
    render = torch.where(subject[..., None], colour, background)
    frame = torch.where(subject[..., None], colour, torch.ones(3))  # composited on white
    dilated = square_mask(size, 6, 18)
    target = torch.where(dilated[..., None], frame, background)
    assert image_loss(render, target) > 0.01
    image, band_target = mask_band_supervision(render, alpha, background, target, band_pixels(boundary_band(dilated, 2), frame, 1.0))
    assert image_loss(image, band_target) < 1e-6
    # with the exact mask the band changes nothing where the render is right
    exact_target = torch.where(subject[..., None], frame, background)
    image, band_target = mask_band_supervision(render, alpha, background, exact_target, band_pixels(boundary_band(subject, 2), frame, 1.0))
    assert image_loss(image, band_target) < 1e-6
    # a render that leaves the subject's edge transparent, or spills past it, costs in the band
    for wrong_alpha in (square_mask(size, 10, 14).float(), square_mask(size, 6, 18).float()):
        wrong = torch.where(wrong_alpha[..., None] > 0, colour, background)
        image, band_target = mask_band_supervision(wrong, wrong_alpha, background, exact_target, band_pixels(boundary_band(subject, 2), frame, 1.0))
        assert image_loss(image, band_target) > 0.01


def test_mask_band_supervision_over_a_filmed_backdrop_recovers_an_eroded_and_a_dilated_mask() -> None:
    # The subject is the square 8..16 filmed in front of a room (random colours); the frame is as filmed.
    # Against masks eroded or dilated by 2 px, the render of the true square, composited over the room in the
    # band, matches the frame exactly; a render that follows the eroded mask leaves room pixels where the
    # frame shows the subject, and costs.
    size, background = 24, torch.tensor([0.2, 0.5, 0.9])
    generator = torch.Generator().manual_seed(0)
    room = torch.rand(size, size, 3, generator=generator)
    subject = square_mask(size, 8, 16)
    colour = torch.tensor([0.7, 0.1, 0.3])
    filmed = torch.where(subject[..., None], colour, room)
    render = torch.where(subject[..., None], colour, background)
    for wrong_mask in (square_mask(size, 10, 14), square_mask(size, 6, 18)):
        target = torch.where(wrong_mask[..., None], filmed, background)
        image, band_target = mask_band_supervision(render, subject.float(), background, target, band_pixels(boundary_band(wrong_mask, 2), filmed, room))
        assert image_loss(image, band_target) < 1e-6
    eroded = square_mask(size, 10, 14)
    thin = torch.where(eroded[..., None], colour, background)
    target = torch.where(eroded[..., None], filmed, background)
    image, band_target = mask_band_supervision(thin, eroded.float(), background, target, band_pixels(boundary_band(eroded, 2), filmed, room))
    assert image_loss(image, band_target) > 0.01


def test_where_the_backdrop_is_unknown_the_mask_decides_in_the_band() -> None:
    size, background = 24, torch.tensor([0.2, 0.5, 0.9])
    subject = square_mask(size, 8, 16)
    frame = torch.where(subject[..., None], torch.tensor([0.7, 0.1, 0.3]), 0.5)
    target = torch.where(subject[..., None], frame, background)
    render, alpha = torch.rand(size, size, 3), torch.rand(size, size)
    backdrop = torch.full((size, size, 3), 0.5)
    backdrop[:, :12] = float("nan")  # the left half unknown
    image, band_target = mask_band_supervision(render, alpha, background, target, band_pixels(boundary_band(subject, 2), frame, backdrop))
    assert torch.equal(image[:, :12], render[:, :12]) and torch.equal(band_target[:, :12], target[:, :12])
    band = boundary_band(subject, 2)[:, 12:]
    assert not torch.equal(image[:, 12:][band], render[:, 12:][band])
