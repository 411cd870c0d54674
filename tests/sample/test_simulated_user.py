"""The simulated user: what it paints, in which colours, within which budget, with a soft brush."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

from avatarperfect_cli.datasets import load_people_snapshot
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.io import read_image, write_image
from avatarperfect_cli.render.mesh_raster import MeshRender
from avatarperfect_cli.sample.simulated_user import PaintResult, UserConfig, paint
from avatarperfect_cli.sample.subject import SyntheticSubject
from avatarperfect_cli.sample.texture import REGION
from avatarperfect_cli.training.metrics import psnr

SAMPLE = Path(__file__).resolve().parents[2] / "examples" / "sample"
BODY_COLOUR = (0.2, 0.3, 0.7)


@dataclass
class Scene:
    """A striped rectangle "subject" and an avatar render of it with known faults (boolean masks)."""

    truth: MeshRender
    suggested: torch.Tensor  # (H, W, 3) quantised to 8 bits, as read from a PNG
    alpha: torch.Tensor
    floater: np.ndarray  # grey blob in the background: paint white
    halo: np.ndarray  # body colour spilling past the silhouette: paint white
    patch: np.ndarray  # wrong colour on the body: paint the true colour
    hole: np.ndarray  # body missing (white): paint the true colour
    speck: np.ndarray  # 3x3 floater: too small to bother
    line: np.ndarray  # 1 px wide floater: too thin to bother


def _box(rows: slice, cols: slice, size: tuple[int, int] = (80, 96)) -> np.ndarray:
    mask = np.zeros(size, bool)
    mask[rows, cols] = True
    return mask


def _scene() -> Scene:
    height, width = 80, 96
    body = _box(slice(16, 64), slice(16, 56))
    columns = np.broadcast_to(np.arange(width), (height, width))
    stripes = np.where(((columns // 3) % 2 == 0)[..., None], (0.8, 0.2, 0.2), BODY_COLOUR)
    truth_rgb = np.where(body[..., None], stripes, 1.0).astype(np.float32)
    truth = MeshRender(truth_rgb, body.astype(np.float32), None)
    faults = {
        "floater": _box(slice(4, 14), slice(62, 76)),
        "halo": _box(slice(36, 50), slice(56, 61)),
        "patch": _box(slice(22, 32), slice(22, 30)),
        "hole": _box(slice(50, 58), slice(36, 44)),
        "speck": _box(slice(68, 71), slice(4, 7)),
        "line": _box(slice(75, 76), slice(20, 60)),
    }
    rgb, alpha = truth_rgb.copy(), body.astype(np.float32)
    for name, colour in (("floater", 0.4), ("halo", BODY_COLOUR), ("speck", 0.3), ("line", 0.3)):
        rgb[faults[name]] = colour
        alpha[faults[name]] = 1.0
    rgb[faults["patch"]] = (0.1, 0.8, 0.1)
    rgb[faults["hole"]] = 1.0
    alpha[faults["hole"]] = 0.0
    suggested = torch.from_numpy(np.round(rgb * 255.0).astype(np.uint8)).float() / 255.0
    return Scene(truth, suggested, torch.from_numpy(alpha), **faults)


def _paint(scene: Scene, **config: object) -> PaintResult:
    return paint(scene.suggested, scene.alpha, scene.truth, UserConfig(**config))


def _blobs(weight: np.ndarray) -> list[np.ndarray]:
    """The fully painted regions, as separate masks."""
    count, labels = cv2.connectedComponents((weight == 1.0).astype(np.uint8), connectivity=8)
    return [labels == label for label in range(1, count)]


def _blob_at(weight: np.ndarray, mask: np.ndarray) -> np.ndarray:
    (blob,) = [blob for blob in _blobs(weight) if (blob & mask).any()]
    return blob


def test_exact_painter_whitens_what_should_be_background_and_paints_true_colours() -> None:
    scene = _scene()
    result = _paint(scene, budget=1.0)
    image, weight, suggested = result.image.numpy(), result.stroke_weight.numpy(), scene.suggested.numpy()
    for fault in (scene.floater, scene.halo):
        np.testing.assert_array_equal(image[fault], 1.0)
    for fault in (scene.patch, scene.hole):
        np.testing.assert_array_equal(image[fault], scene.truth.rgb[fault])
    # Specks and thin lines stay, and nothing far from a fault is touched.
    for fault in (scene.speck, scene.line):
        np.testing.assert_array_equal(image[fault], suggested[fault])
    painted_faults = scene.floater | scene.halo | scene.patch | scene.hole
    near = cv2.dilate(painted_faults.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    assert (weight[~near] == 0).all()
    np.testing.assert_array_equal(image[weight == 0], suggested[weight == 0])
    stats = result.stats
    assert stats.painted_by_kind["background"] == scene.floater.sum() + scene.halo.sum()
    assert stats.painted_by_kind["missing"] == scene.hole.sum()
    assert stats.painted_by_kind["colour"] >= scene.patch.sum()
    assert stats.wrong_pixels == stats.painted_by_kind
    assert stats.blobs_found == stats.blobs_painted == 4
    assert stats.painted_pixels == (weight > 0).sum()


def test_flat_painter_uses_each_blobs_mean_true_colour() -> None:
    scene = _scene()
    flat = _paint(scene, style="flat", budget=1.0)
    exact = _paint(scene, style="exact", budget=1.0)
    image, weight = flat.image.numpy(), flat.stroke_weight.numpy()
    np.testing.assert_array_equal(image[scene.floater], 1.0)
    for fault in (scene.patch, scene.hole):
        blob = _blob_at(weight, fault)
        expected = scene.truth.rgb[blob].astype(np.float64).mean(axis=0)
        np.testing.assert_allclose(image[blob], np.broadcast_to(expected, image[blob].shape), atol=1e-6)
    # The stripes under the patch: exact paints them, flat paints one colour.
    assert len(np.unique(exact.image.numpy()[scene.patch], axis=0)) == 2
    assert len(np.unique(image[scene.patch], axis=0)) == 1
    np.testing.assert_array_equal(weight, exact.stroke_weight.numpy())


def test_the_edited_png_keeps_every_byte_outside_the_strokes(tmp_path: Path) -> None:
    scene = _scene()
    write_image(tmp_path / "suggested.png", scene.suggested)
    suggested = read_image(tmp_path / "suggested.png")
    result = paint(suggested, scene.alpha, scene.truth, UserConfig())
    write_image(tmp_path / "edited.png", result.image)
    before = np.asarray(Image.open(tmp_path / "suggested.png"))
    after = np.asarray(Image.open(tmp_path / "edited.png"))
    untouched = result.stroke_weight.numpy() == 0
    assert untouched.any() and not untouched.all()
    np.testing.assert_array_equal(after[untouched], before[untouched])
    assert (after[~untouched] != before[~untouched]).any()


def test_budget_paints_the_largest_blobs_that_fit_first() -> None:
    scene = _scene()
    everything = _paint(scene, budget=1.0)
    subject_pixels = int(((scene.truth.coverage >= 0.5) | (scene.alpha.numpy() > 0.5)).sum())
    assert everything.stats.subject_pixels == subject_pixels
    blobs = sorted(_blobs(everything.stroke_weight.numpy()), key=lambda blob: -blob.sum())
    areas = [int(blob.sum()) for blob in blobs]
    assert len(blobs) == 4 and len(set(areas)) == 4
    # A 1 px feather reaches the 8 neighbours of a blob's pixels.
    strokes = [int(cv2.dilate(blob.astype(np.uint8), np.ones((3, 3), np.uint8)).sum()) for blob in blobs]
    budget_pixels = strokes[0] + strokes[3]  # the largest and the smallest; the middle two do not fit
    assert strokes[0] + strokes[2] > budget_pixels
    result = _paint(scene, budget=(budget_pixels + 0.5) / subject_pixels, priority="area")
    assert result.stats.budget_pixels == budget_pixels
    np.testing.assert_array_equal(result.stroke_weight.numpy() == 1.0, blobs[0] | blobs[3])
    changed = (result.image.numpy() != scene.suggested.numpy()).any(axis=2)
    assert result.stats.painted_pixels == budget_pixels and changed.sum() <= budget_pixels
    assert result.stats.blobs_painted == 2 and result.stats.budget_used == 1.0
    # The default 15 % budget holds too.
    default = _paint(scene)
    assert 0 < default.stats.painted_pixels <= default.stats.budget_pixels == int(0.15 * subject_pixels)


def _faint_and_strong_scene() -> tuple[MeshRender, torch.Tensor, torch.Tensor, np.ndarray, np.ndarray]:
    """A flat body with a large, faintly wrong patch (20 x 20 px, 0.12 off) and a small floater off the
    body (10 x 10 px, 0.8 off): the truth, the suggested render, its alpha and the two masks."""
    body = _box(slice(10, 70), slice(10, 50))
    truth_rgb = np.where(body[..., None], np.full(3, 0.5, np.float32), np.ones(3, np.float32))
    faint, strong = _box(slice(20, 40), slice(20, 40)), _box(slice(30, 40), slice(70, 80))
    rgb, alpha = truth_rgb.copy(), body.astype(np.float32)
    rgb[faint] = 0.62
    rgb[strong] = 0.2
    alpha[strong] = 1.0
    return MeshRender(truth_rgb, body.astype(np.float32), None), _quantised(rgb), torch.from_numpy(alpha), faint, strong


@pytest.mark.parametrize("priority", ["area", "error"])
def test_priority_decides_which_blob_a_tight_budget_paints(priority: str) -> None:
    truth, suggested, alpha, faint, strong = _faint_and_strong_scene()
    subject_pixels = int(((truth.coverage >= 0.5) | (alpha.numpy() > 0.5)).sum())
    both = paint(suggested, alpha, truth, UserConfig(budget=1.0, priority=priority))
    blobs = _blobs(both.stroke_weight.numpy())
    assert len(blobs) == 2 and blobs[0].any()
    # Room for the larger blob's stroke (the blob and its 1 px feather), so for either blob but not both.
    strokes = [int(cv2.dilate(blob.astype(np.uint8), np.ones((3, 3), np.uint8)).sum()) for blob in blobs]
    result = paint(suggested, alpha, truth, UserConfig(budget=(max(strokes) + 0.5) / subject_pixels, priority=priority))
    painted = result.stroke_weight.numpy() == 1.0
    assert result.stats.blobs_painted == 1
    # area: the large faint patch first; error (summed difference): the small glaring floater first
    expected, other = (faint, strong) if priority == "area" else (strong, faint)
    assert painted[expected].mean() > 0.8 and not painted[other].any()


def test_when_no_blob_fits_the_worst_spot_of_the_first_is_painted() -> None:
    """A budget under every blob's stroke: the user paints the first blob (the glaring floater) around its
    most wrong pixel as far as the budget goes, not nothing, and still reports every wrong pixel found."""
    truth, suggested, alpha, faint, strong = _faint_and_strong_scene()
    subject_pixels = int(((truth.coverage >= 0.5) | (alpha.numpy() > 0.5)).sum())
    everything = paint(suggested, alpha, truth, UserConfig(budget=1.0))
    strokes = [int(cv2.dilate(blob.astype(np.uint8), np.ones((3, 3), np.uint8)).sum()) for blob in _blobs(everything.stroke_weight.numpy())]
    budget_pixels = min(strokes) // 2
    result = paint(suggested, alpha, truth, UserConfig(budget=(budget_pixels + 0.5) / subject_pixels))
    painted = result.stroke_weight.numpy() == 1.0
    assert result.stats.budget_pixels == budget_pixels and result.stats.blobs_painted == 1
    assert 0 < result.stats.painted_pixels <= budget_pixels
    assert painted.any() and not painted[~strong].any() and painted.sum() >= 0.3 * budget_pixels
    assert len(_blobs(result.stroke_weight.numpy())) == 1, "one stroke around the worst spot"
    np.testing.assert_array_equal(result.image.numpy()[painted], np.ones((int(painted.sum()), 3), np.float32))
    assert result.stats.wrong_pixels == everything.stats.wrong_pixels
    # Not even one pixel's stroke fits: nothing is painted.
    tiny = paint(suggested, alpha, truth, UserConfig(budget=2.5 / subject_pixels))
    assert tiny.stats.painted_pixels == 0 and torch.equal(tiny.image, suggested)


@pytest.mark.parametrize("feather", [0.0, 1.0, 2.0])
def test_strokes_have_a_soft_edge_of_the_feather_width(feather: float) -> None:
    scene = _scene()
    result = _paint(scene, budget=1.0, brush_feather_px=feather)
    weight = result.stroke_weight.numpy()
    interior = weight == 1.0
    distance = cv2.distanceTransform((~interior).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    expected = np.clip(1.0 - distance / (feather + 1.0), 0.0, 1.0)
    np.testing.assert_allclose(weight, expected, atol=1e-6)
    soft = (weight > 0) & (weight < 1)
    assert soft.any() == (feather > 0)
    if feather == 1.0:
        # Just inside the body, left of the whitened halo: half the body colour, half white.
        suggested = scene.suggested.numpy()[40, 55]
        np.testing.assert_allclose(result.image.numpy()[40, 55], 0.5 * suggested + 0.5, atol=1e-6)
        assert np.abs(result.image.numpy()[40, 55] - suggested).max() > 10 / 255  # apply-edit sees it


def test_min_region_pixels_decides_what_counts_as_a_speck() -> None:
    scene = _scene()
    assert (_paint(scene, budget=1.0, min_region_pixels=9).image.numpy()[scene.speck] == 1.0).all()
    assert (_paint(scene, budget=1.0, min_region_pixels=10).image.numpy()[scene.speck] != 1.0).all()


def test_painting_is_deterministic() -> None:
    first, second = _paint(_scene(), style="flat"), _paint(_scene(), style="flat")
    assert torch.equal(first.image, second.image) and torch.equal(first.stroke_weight, second.stroke_weight)
    assert asdict(first.stats) == asdict(second.stats)


@pytest.mark.parametrize(("tolerance_px", "outline_painted"), [(0, True), (2, True), (3, False), (5, False)])
def test_an_outline_a_few_pixels_off_is_overlooked_within_the_tolerance(tolerance_px: int, outline_painted: bool) -> None:
    """The avatar drawn 3 px right of the truth, stripes and all: within the tolerance nothing of that is
    painted (a person sees nothing wrong), beyond it the uncovered edge is; the floater, the green patch and
    the hole are painted either way."""
    scene = _scene()
    suggested = torch.roll(scene.suggested, 3, dims=1)
    alpha = torch.roll(scene.alpha, 3, dims=1)
    shifted = {name: np.roll(getattr(scene, name), 3, axis=1) for name in ("floater", "patch", "hole", "halo")}
    height = scene.suggested.shape[0]
    result = paint(suggested, alpha, scene.truth, UserConfig(budget=1.0, outline_tolerance=tolerance_px / height))
    weight = result.stroke_weight.numpy()
    uncovered = _box(slice(20, 60), slice(16, 19))  # the body's left edge the shift leaves white
    assert (weight[uncovered] == 1.0).all() if outline_painted else (weight[uncovered] == 0.0).all()
    for name in ("floater", "patch", "hole"):
        assert (weight[shifted[name]] == 1.0).all()
    if not outline_painted:
        near_faults = cv2.dilate((shifted["patch"] | shifted["hole"]).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        away_from_halo = _box(slice(16, 64), slice(19, 52))  # the halo's blob reaches 3 px into the body, as it should
        assert (weight[away_from_halo & ~near_faults] == 0.0).all()


@pytest.mark.parametrize(
    "config",
    [{"style": "sketchy"}, {"budget": 0.0}, {"budget": 1.5}, {"brush_feather_px": -1.0}, {"priority": "loudest"},
     {"outline_tolerance": -0.01}, {"outline_tolerance": 0.5}],
)  # fmt: skip
def test_bad_settings_are_one_line_errors(config: dict) -> None:
    with pytest.raises(AvatarPerfectError, match=r"^[^\n]+$"):
        UserConfig(**config)


@pytest.fixture(scope="module")
def held_out_truth() -> MeshRender:
    """The committed sample's subject in test frame 7 (arms away from the body: inner arms in view)."""
    video = load_people_snapshot(SAMPLE / "test")
    subject = SyntheticSubject.from_dataset(SAMPLE / "test")
    return subject.render(video.body_pose[7], video.transl[7], video.camera)


def _quantised(rgb: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.round(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8)).float() / 255.0


def test_a_correct_render_gets_no_paint(held_out_truth: MeshRender) -> None:
    suggested = _quantised(held_out_truth.rgb)
    result = paint(suggested, torch.from_numpy(held_out_truth.coverage), held_out_truth, UserConfig())
    assert result.stats.blobs_found == 0 and torch.equal(result.image, suggested)


@pytest.mark.parametrize("style", ["exact", "flat"])
def test_painting_a_damaged_render_brings_it_closer_to_the_truth(held_out_truth: MeshRender, style: str) -> None:
    truth = held_out_truth
    inner_arm = truth.labels == REGION["inner_arm"]
    rows, cols = np.mgrid[: truth.coverage.shape[0], : truth.coverage.shape[1]]
    floater = (rows - 40) ** 2 + (cols - 40) ** 2 <= 36
    assert inner_arm.sum() > 200 and not (floater & (truth.coverage > 0)).any()
    damaged, alpha = truth.rgb.copy(), truth.coverage.copy()
    damaged[inner_arm] = (0.77, 0.59, 0.48)  # the avatar guessed skin
    damaged[floater], alpha[floater] = 0.35, 1.0
    suggested = _quantised(damaged)
    result = paint(suggested, torch.from_numpy(alpha), truth, UserConfig(style=style))
    target = torch.from_numpy(truth.rgb)
    arm = torch.from_numpy(inner_arm)
    assert psnr(result.image, target) > psnr(suggested, target) + 5.0
    assert psnr(result.image[arm], target[arm]) > psnr(suggested[arm], target[arm]) + 4.0
    np.testing.assert_array_equal(result.image.numpy()[floater], 1.0)
    assert result.stats.painted_pixels <= result.stats.budget_pixels
    assert result.stats.painted_by_kind["background"] == floater.sum()
