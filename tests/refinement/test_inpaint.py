import json
import sys
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from PIL import Image

from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.refinement import inpaint
from avatarperfect_cli.refinement.inpaint import fill_diffusion, fill_flat, fill_opencv, parse_colour


@pytest.mark.parametrize(
    "text,expected",
    [
        ("white", (255, 255, 255)),
        ("Black", (0, 0, 0)),
        ("#ff8000", (255, 128, 0)),
        ("#0f0", (0, 255, 0)),
        ("255,128,0", (255, 128, 0)),
        (" 10 , 20 , 30 ", (10, 20, 30)),
        ("1,1,1", (1, 1, 1)),  # integers are levels, even when small
        ("1.0,0.5,0", (255, 127.5, 0)),
        ("0.25,0.5,0.75", (63.75, 127.5, 191.25)),
    ],
)
def test_parse_colour(text: str, expected: tuple[float, float, float]) -> None:
    assert parse_colour(text) == pytest.approx(tuple(value / 255.0 for value in expected))


@pytest.mark.parametrize("text", ["", "whiteish", "#12345", "256,0,0", "1,2", "1,2,3,4", "-1,0,0", "0.5,0.5,2.5"])
def test_parse_colour_rejects(text: str) -> None:
    with pytest.raises(AvatarPerfectError) as error:
        parse_colour(text)
    assert "\n" not in str(error.value)


def smooth_image(height: int, width: int) -> torch.Tensor:
    """(H, W, 3) float32: a plane per channel, which fills from the surroundings should continue."""
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32), indexing="ij"
    )
    return torch.stack(
        [0.2 + 0.5 * xs / width, 0.7 - 0.4 * ys / height, 0.3 + 0.2 * (xs + ys) / (width + height)], dim=-1
    )


def disk(height: int, width: int, centre: tuple[int, int], radius: float) -> torch.Tensor:
    ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    return (ys - centre[0]) ** 2 + (xs - centre[1]) ** 2 <= radius**2


def test_fill_flat_sets_exactly_the_region() -> None:
    image = torch.rand(20, 30, 3)
    region = disk(20, 30, (8, 12), 5)
    filled = fill_flat(image, region, (0.1, 0.2, 0.3))
    assert torch.equal(filled[~region], image[~region])
    assert torch.equal(filled[region], torch.tensor([0.1, 0.2, 0.3]).expand(int(region.sum()), 3))
    assert not torch.equal(image, filled)  # a copy, the input is untouched
    with pytest.raises(AvatarPerfectError):
        fill_flat(image, torch.zeros(20, 31, dtype=torch.bool), (0.0, 0.0, 0.0))


@pytest.mark.parametrize("method", ["telea", "ns"])
def test_fill_opencv_continues_the_surroundings(method: str) -> None:
    image = smooth_image(48, 64)
    region = disk(48, 64, (24, 30), 7)
    damaged = image.clone()
    damaged[region] = torch.tensor([1.0, 0.0, 1.0])  # an artifact the fill must not see
    filled = fill_opencv(damaged, region, method)
    assert torch.equal(filled[~region], damaged[~region])
    assert (filled[region] - image[region]).abs().max() < 0.04  # red changes by 0.11 across the disk
    assert (damaged[region] - image[region]).abs().min() > 0.2


def test_fill_opencv_edge_cases() -> None:
    image = torch.rand(8, 8, 3)
    assert torch.equal(fill_opencv(image, torch.zeros(8, 8, dtype=torch.bool), "telea"), image)
    with pytest.raises(AvatarPerfectError, match="whole image"):
        fill_opencv(image, torch.ones(8, 8, dtype=torch.bool), "telea")
    with pytest.raises(AvatarPerfectError, match="telea"):
        fill_opencv(image, torch.zeros(8, 8, dtype=torch.bool), "blur")


def test_fill_diffusion_folder_errors(tmp_path: Path) -> None:
    image, region = torch.rand(16, 16, 3), disk(16, 16, (8, 8), 3)
    with pytest.raises(InputFileError, match="model_index.json") as error:
        fill_diffusion(image, region, tmp_path)
    assert "\n" not in str(error.value)
    pytest.importorskip("diffusers")
    (tmp_path / "model_index.json").write_text(json.dumps({"_class_name": "StableDiffusionInpaintPipeline"}))
    with pytest.raises(InputFileError) as error:
        fill_diffusion(image, region, tmp_path)
    assert "\n" not in str(error.value) and str(tmp_path) in str(error.value)


def test_fill_diffusion_without_diffusers_names_the_extra(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "model_index.json").write_text("{}")
    monkeypatch.setitem(sys.modules, "diffusers", None)  # import diffusers now raises ImportError
    with pytest.raises(AvatarPerfectError, match=r"pip install \"avatarperfect-cli\[inpaint\]\""):
        fill_diffusion(torch.rand(16, 16, 3), disk(16, 16, (8, 8), 3), tmp_path)


class EchoPipeline:
    """Stands in for a diffusers pipeline with 128 px native images (the smallest crop, so nothing is resampled):
    returns its input image, black under the repaint mask when `blacken` is set."""

    unet = SimpleNamespace(config=SimpleNamespace(sample_size=64))
    vae_scale_factor = 2
    device = torch.device("cpu")

    def __init__(self, blacken: bool) -> None:
        self.blacken = blacken

    def __call__(
        self, image: Image.Image, mask_image: Image.Image, height: int, width: int, **_: object
    ) -> SimpleNamespace:
        assert image.size == mask_image.size == (width, height) == (128, 128)
        pixels = np.asarray(image, dtype=np.float32) / 255.0
        if self.blacken:
            pixels = pixels * (np.asarray(mask_image)[..., None] == 0)
        return SimpleNamespace(images=[pixels])


@pytest.mark.parametrize("height,width,centre", [(160, 200, (80, 90)), (160, 200, (3, 196)), (40, 56, (20, 30))])
def test_fill_diffusion_crops_and_pastes_in_place(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, height: int, width: int, centre: tuple[int, int]
) -> None:
    image = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(2))
    region = disk(height, width, centre, 9)
    monkeypatch.setattr(inpaint, "_load_pipeline", lambda folder: EchoPipeline(blacken=False))
    echoed = fill_diffusion(image, region, tmp_path, candidates=1)[0]
    assert (echoed - image).abs().max() <= 0.5 / 255.0 + 1e-6  # the crop went back where it came from
    monkeypatch.setattr(inpaint, "_load_pipeline", lambda folder: EchoPipeline(blacken=True))
    blackened = fill_diffusion(image, region, tmp_path, candidates=1)[0]
    assert (blackened[region] == 0.0).all() and torch.equal(blackened[~region], image[~region])  # the mask covers it


def write_tiny_inpainting_pipeline(folder: Path) -> None:
    """A randomly initialised Stable-Diffusion inpainting pipeline with 32 px native images, saved to `folder`."""
    diffusers = pytest.importorskip("diffusers")
    transformers = pytest.importorskip("transformers")
    torch.manual_seed(0)
    unet = diffusers.UNet2DConditionModel(
        sample_size=16,
        in_channels=9,  # noisy latents, mask, masked-image latents
        out_channels=4,
        block_out_channels=(8, 16),
        layers_per_block=1,
        down_block_types=("DownBlock2D", "CrossAttnDownBlock2D"),
        up_block_types=("CrossAttnUpBlock2D", "UpBlock2D"),
        cross_attention_dim=16,
        attention_head_dim=2,
        norm_num_groups=4,
    )
    vae = diffusers.AutoencoderKL(
        in_channels=3,
        out_channels=3,
        block_out_channels=(8, 16),
        down_block_types=("DownEncoderBlock2D",) * 2,
        up_block_types=("UpDecoderBlock2D",) * 2,
        latent_channels=4,
        norm_num_groups=4,
    )
    text_encoder = transformers.CLIPTextModel(
        transformers.CLIPTextConfig(
            vocab_size=64,
            hidden_size=16,
            intermediate_size=32,
            num_attention_heads=2,
            num_hidden_layers=1,
            max_position_embeddings=77,
            bos_token_id=0,
            pad_token_id=1,
            eos_token_id=2,
        )
    )
    vocabulary = {"<|startoftext|>": 0, "!": 1, "<|endoftext|>": 2}
    for letter in "abcdefghijklmnopqrstuvwxyz":
        vocabulary[letter] = len(vocabulary)
        vocabulary[f"{letter}</w>"] = len(vocabulary)
    (folder / "tokens").mkdir()
    (folder / "tokens" / "vocab.json").write_text(json.dumps(vocabulary))
    (folder / "tokens" / "merges.txt").write_text("#version: 0.2\n")
    tokenizer = transformers.CLIPTokenizer(
        str(folder / "tokens" / "vocab.json"), str(folder / "tokens" / "merges.txt"), model_max_length=77
    )
    scheduler = diffusers.DDIMScheduler(
        beta_schedule="scaled_linear", beta_start=0.00085, beta_end=0.012, steps_offset=1, clip_sample=False
    )
    pipeline = diffusers.StableDiffusionInpaintPipeline(
        vae=vae,
        text_encoder=text_encoder,
        tokenizer=tokenizer,
        unet=unet,
        scheduler=scheduler,
        safety_checker=None,
        feature_extractor=None,
        requires_safety_checker=False,
    )
    pipeline.save_pretrained(folder / "pipeline")


@pytest.fixture(scope="module")
def tiny_pipeline(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The tiny pipeline's folder; torch on one thread meanwhile (its ops are too small to share, and on a busy
    machine two threads made each run 60x slower)."""
    folder = tmp_path_factory.mktemp("inpainting")
    write_tiny_inpainting_pipeline(folder)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield folder / "pipeline"
    torch.set_num_threads(threads)


@pytest.mark.parametrize(
    "height,width,centre",
    [(160, 200, (80, 90)), (160, 200, (3, 196)), (40, 56, (20, 30))],  # middle, corner, image smaller than the crop
)
def test_fill_diffusion_candidates(tiny_pipeline: Path, height: int, width: int, centre: tuple[int, int]) -> None:
    image = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(1))
    region = disk(height, width, centre, 6)
    progress: list[tuple[int, int]] = []
    candidates = fill_diffusion(
        image,
        region,
        tiny_pipeline,
        prompt="a red shirt",
        candidates=3,
        seed=5,
        steps=2,
        on_step=lambda done, total: progress.append((done, total)),
    )
    assert len(candidates) == 3 and progress == [(done, 6) for done in range(1, 7)]
    for candidate in candidates:
        assert candidate.shape == image.shape and candidate.dtype == image.dtype
        assert torch.equal(candidate[~region], image[~region])
        assert candidate.min() >= 0.0 and candidate.max() <= 1.0
    for first, second in [(0, 1), (0, 2), (1, 2)]:
        assert (candidates[first][region] - candidates[second][region]).abs().mean() > 1e-3
    again = fill_diffusion(image, region, tiny_pipeline, prompt="a red shirt", candidates=1, seed=6, steps=2)
    assert torch.equal(again[0], candidates[1])  # candidate i comes from seed + i alone
