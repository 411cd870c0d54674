from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from avatarperfect_cli.errors import InputFileError
from avatarperfect_cli.io.images import read_image, whole_image, write_image


def pil_mode_and_pixels(path: Path) -> tuple[str, np.ndarray]:
    with Image.open(path) as image:
        return image.mode, np.asarray(image)


def all_levels(height: int, width: int, channels: int) -> torch.Tensor:
    """(H, W, C) float32 image whose values k / 255 cover every 8-bit level."""
    levels = torch.arange(height * width * channels) % 256
    return (levels.to(torch.float32) / 255.0).reshape(height, width, channels)


@pytest.mark.parametrize("channels,mode", [(3, "RGB"), (4, "RGBA")])
def test_round_trip_is_exact(tmp_path: Path, channels: int, mode: str) -> None:
    image = all_levels(16, 24, channels)
    write_image(tmp_path / "render.png", image)
    loaded = read_image(tmp_path / "render.png")
    assert loaded.dtype == torch.float32 and loaded.shape == (16, 24, channels)
    assert torch.equal(loaded, image)
    assert pil_mode_and_pixels(tmp_path / "render.png")[0] == mode
    assert sorted(p.name for p in tmp_path.iterdir()) == ["render.png"]


@pytest.mark.parametrize("shape", [(16, 16), (16, 16, 1)])
def test_gray_round_trip(tmp_path: Path, shape: tuple[int, ...]) -> None:
    image = all_levels(16, 16, 1).reshape(shape)
    write_image(tmp_path / "mask.png", image)
    assert pil_mode_and_pixels(tmp_path / "mask.png")[0] == "L"
    assert torch.equal(read_image(tmp_path / "mask.png", mode="L"), image.reshape(16, 16, 1))
    rgb = read_image(tmp_path / "mask.png")  # no alpha: RGB with three equal channels
    assert torch.equal(rgb, image.reshape(16, 16, 1).expand(16, 16, 3))


def test_modes_drop_or_add_alpha(tmp_path: Path) -> None:
    image = all_levels(4, 5, 4)
    write_image(tmp_path / "a.png", image)
    assert torch.equal(read_image(tmp_path / "a.png", mode="RGB"), image[..., :3])
    write_image(tmp_path / "b.png", image[..., :3])
    with_alpha = read_image(tmp_path / "b.png", mode="RGBA")
    assert torch.equal(with_alpha[..., :3], image[..., :3]) and torch.equal(with_alpha[..., 3], torch.ones(4, 5))


def test_values_are_clipped_and_rounded(tmp_path: Path) -> None:
    image = torch.tensor([[[-0.3, 1.7, 0.5 / 255.0 + 1e-4]]])
    write_image(tmp_path / "a.png", image)
    assert pil_mode_and_pixels(tmp_path / "a.png")[1].tolist() == [[[0, 255, 1]]]


def test_sixteen_bit_gray_keeps_its_precision(tmp_path: Path) -> None:
    values = np.array([[0, 1000, 40000, 65535]], dtype=np.uint16)
    Image.fromarray(values).save(tmp_path / "mask16.png")
    loaded = read_image(tmp_path / "mask16.png", mode="L")
    assert torch.allclose(loaded[..., 0], torch.from_numpy(values.astype(np.float64) / 65535.0).float())
    assert read_image(tmp_path / "mask16.png").shape == (1, 4, 3)


def test_write_refuses_bad_shapes_and_values(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="shape"):
        write_image(tmp_path / "a.png", torch.zeros(4, 4, 2))
    with pytest.raises(ValueError, match="NaN"):
        write_image(tmp_path / "a.png", torch.full((2, 2, 3), float("nan")))
    assert list(tmp_path.iterdir()) == []


def _truncated_png(path: Path) -> Path:
    write_image(path, torch.rand(64, 64, 3, generator=torch.Generator().manual_seed(0)))
    path.write_bytes(path.read_bytes()[:200])
    return path


def _directory(path: Path) -> Path:
    path.mkdir()
    return path


def _text(path: Path) -> Path:
    path.write_text("not an image")
    return path


def _float_tiff(path: Path) -> Path:
    Image.fromarray(np.zeros((2, 3), dtype=np.float32)).save(path, format="TIFF")
    return path


BAD_FILES = {
    "missing": (lambda p: p, "file not found"),
    "directory": (_directory, "not a regular file"),
    "text": (_text, "not a readable image"),
    "float pixels": (_float_tiff, "unsupported pixel format 'F'"),
    "truncated": (_truncated_png, "not a readable image"),
}


@pytest.mark.parametrize("case", BAD_FILES)
def test_bad_file_gives_input_file_error(tmp_path: Path, case: str) -> None:
    make, problem = BAD_FILES[case]
    path = make(tmp_path / "edited.png")
    with pytest.raises(InputFileError) as caught:
        read_image(path)
    message = str(caught.value)
    assert "edited.png" in message and problem in message and "\n" not in message


@pytest.mark.parametrize("suffix", [".png", ".jpg", ".webp"])
def test_whole_image_is_false_for_every_cut_of_a_save(tmp_path: Path, suffix: str) -> None:
    """A file cut anywhere (an editor still writing it) is not whole; the complete file is."""
    path = tmp_path / f"painted{suffix}"
    write_image(path, torch.rand(24, 32, 3, generator=torch.Generator().manual_seed(0)))
    data = path.read_bytes()
    assert whole_image(path)
    for cut in range(0, len(data), max(1, len(data) // 40)):
        path.write_bytes(data[:cut])
        assert not whole_image(path), f"{cut} of {len(data)} bytes"
    path.write_bytes(data[:-1])
    assert not whole_image(path)
    assert not whole_image(tmp_path / "missing.png")
