"""The silhouette distances: the projection, the nearest-point kernel and the fused loss kernel against
independent references (dense PyTorch, float64, gradcheck), and the distances of a posed body against its own
masks and against moved masks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from avatarperfect_cli.body import forward_kinematics, load_body_template, skin_points
from avatarperfect_cli.datasets import FrameRange, VideoDataset, load_people_snapshot
from avatarperfect_cli.render import Camera
from avatarperfect_cli.training.silhouette import Silhouettes, _nearest_kernel, project, silhouette_loss, silhouettes

SAMPLE = Path(__file__).resolve().parents[2] / "examples" / "sample" / "train"


def _turned_camera() -> Camera:
    """A camera turned about a tilted axis and moved, with unequal focal lengths and an off-centre principal point."""
    axis = torch.tensor([0.3, -0.8, 0.2], dtype=torch.float64)
    angle = 0.7
    k = torch.tensor([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]]) / axis.norm()
    world_to_camera = torch.eye(4, dtype=torch.float64)
    world_to_camera[:3, :3] = torch.eye(3, dtype=torch.float64) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
    world_to_camera[:3, 3] = torch.tensor([0.1, -0.2, 3.0], dtype=torch.float64)
    K = torch.tensor([[410.0, 0.0, 61.5], [0.0, 380.0, 47.25], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return Camera(K=K, world_to_camera=world_to_camera, width=120, height=90)


def test_projection_matches_a_pinhole_per_point_and_has_its_gradient() -> None:
    camera = _turned_camera()
    points = torch.randn(2, 7, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 0.5
    pixels = project(points, camera)
    rotation, translation, K = (t.numpy() for t in (camera.world_to_camera[:3, :3], camera.world_to_camera[:3, 3], camera.K))
    for index in np.ndindex(*points.shape[:2]):
        x, y, z = rotation @ points[index].numpy() + translation
        expected = (K[0, 0] * x / z + K[0, 2], K[1, 1] * y / z + K[1, 2])
        np.testing.assert_allclose(pixels[index].numpy(), expected, rtol=1e-12, atol=1e-9)
    assert torch.autograd.gradcheck(lambda p: project(p, camera), points.clone().requires_grad_())


def test_nearest_kernel_matches_brute_force() -> None:
    rng = np.random.default_rng(1)
    points = rng.uniform(-20.0, 120.0, size=(3, 400, 2))  # some outside the 100 x 80 image
    queries = rng.uniform(0.0, 80.0, size=(3, 150, 2))
    nearest = _nearest_kernel(points, queries, 100, 80, 4.0)
    distances = np.linalg.norm(queries[:, :, None] - points[:, None], axis=-1)
    chosen = np.take_along_axis(distances, nearest[..., None], axis=2)[..., 0]
    np.testing.assert_allclose(chosen, distances.min(axis=2), rtol=0, atol=1e-12)


def _reference_loss(posed: torch.Tensor, data: Silhouettes, huber: float) -> torch.Tensor:
    """`silhouette_loss` in dense PyTorch ops (autograd gives its gradient): the outside distances sampled by
    grid_sample, the coverage distances by brute-force nearest points."""
    pixels = project(posed, data.camera)
    size = torch.tensor([data.camera.width, data.camera.height], dtype=pixels.dtype)
    grid = (2.0 * pixels / size - 1.0)[:, :, None]
    sampled = F.grid_sample(data.outside.to(pixels.dtype), grid, mode="bilinear", padding_mode="border", align_corners=False)[:, 0, :, 0]
    beyond = (pixels - pixels.clamp(torch.zeros_like(size), size)).norm(dim=-1)
    x, y = pixels.unbind(-1)
    top, bottom, left, right = (data.cut[:, None, side] for side in range(4))
    unseen = (y < 0) & top | (y > size[1]) & bottom | (x < 0) & left | (x > size[0]) & right
    robust = lambda d: torch.where(d < huber, 0.5 * d * d / huber, d - 0.5 * huber)  # noqa: E731
    outside = robust(torch.where(unseen, 0.0, sampled + beyond)).mean(dim=1)
    contours = data.contours.to(pixels.dtype)
    nearest = torch.cdist(contours, pixels.detach()).argmin(dim=2)
    coverage = (contours - pixels.gather(1, nearest[..., None].expand(-1, -1, 2))).norm(dim=-1)
    return outside + robust(coverage).mean(dim=1)


def _random_silhouettes(cut: list[list[bool]]) -> tuple[torch.Tensor, Silhouettes]:
    """World points (T, 60, 3) float64 in front of `_turned_camera`, some projected past every image edge,
    and silhouettes with random distance fields, contours and cut edges `cut` (T, 4)."""
    generator = torch.Generator().manual_seed(3)
    camera = _turned_camera()
    frames = len(cut)
    pixels = torch.rand(frames, 60, 2, dtype=torch.float64, generator=generator) * torch.tensor([160.0, 130.0]) - torch.tensor([20.0, 20.0])
    depth = 2.0 + torch.rand(frames, 60, 1, dtype=torch.float64, generator=generator)
    in_camera = torch.cat([(pixels - camera.K[:2, 2]) / torch.diagonal(camera.K)[:2] * depth, depth], dim=-1)
    rotation, translation = camera.world_to_camera[:3, :3], camera.world_to_camera[:3, 3]
    posed = (in_camera - translation) @ rotation  # world points whose projections are `pixels`
    outside = torch.rand(frames, 1, camera.height, camera.width, generator=generator) * 6.0
    contours = torch.rand(frames, 25, 2, generator=generator) * torch.tensor([float(camera.width), float(camera.height)])
    data = Silhouettes(camera, torch.zeros(frames, 24, 3), torch.zeros(frames, 3), outside, contours, torch.tensor(cut))
    return posed, data


def test_the_loss_kernel_matches_dense_pytorch_and_its_gradient() -> None:
    """The fused kernel against the dense reference in float64, loss and gradient, with points inside the
    image, past edges the mask touches (unseen) and past edges it does not (charged by how far)."""
    posed, data = _random_silhouettes([[False] * 4, [True, False, True, False], [False, True, False, True]])
    for huber in (0.5, 2.0):
        reference_points = posed.clone().requires_grad_()
        reference = _reference_loss(reference_points, data, huber)
        weights = torch.tensor([0.3, -1.2, 2.0], dtype=torch.float64)
        (reference * weights).sum().backward()
        kernel_points = posed.clone().requires_grad_()
        loss = silhouette_loss(kernel_points, data, huber)
        (loss * weights).sum().backward()
        assert loss.dtype == torch.float64
        torch.testing.assert_close(loss, reference.detach(), rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(kernel_points.grad, reference_points.grad, rtol=1e-8, atol=1e-10)
        assert float(reference_points.grad.abs().max()) > 1e-3  # the comparison is not of zeros


def test_the_loss_kernel_passes_gradcheck() -> None:
    posed, data = _random_silhouettes([[False, True, False, False], [False] * 4])
    assert torch.autograd.gradcheck(lambda p: silhouette_loss(p, data, 2.0), posed.clone().requires_grad_(), atol=1e-6)


def test_the_true_body_is_nearer_its_masks_than_a_moved_one() -> None:
    """The sample's own body, posed by its own poses, lies on its masks (a small fraction of a pixel on
    average); moved 4 cm sideways (about 2 pixels here) it is several times farther, in every frame."""
    video = load_people_snapshot(SAMPLE, FrameRange(0, 59, 10), downscale=1)
    template = load_body_template("anny", phenotype=video.subject["phenotype"])
    data = silhouettes(video, torch.arange(len(video)), 96, 200)
    posed = skin_points(template.vertices, template.weights, forward_kinematics(video.body_pose, template.rest_joints, video.transl))
    on_masks = silhouette_loss(posed, data, huber=2.0)
    moved = silhouette_loss(posed + torch.tensor([0.04, 0.0, 0.0]), data, huber=2.0)
    assert on_masks.shape == (len(video),)
    assert float(on_masks.max()) < 0.1
    assert bool((moved > 3.0 * on_masks).all()), (on_masks, moved)


def _cut_off_below(video: VideoDataset, rows: int) -> VideoDataset:
    """The video with only its top `rows` pixel rows: the camera's image ends there (its intrinsics kept)."""
    camera = Camera(video.camera.K, video.camera.world_to_camera, video.camera.width, rows)
    return VideoDataset(**{**vars(video), "camera": camera, "images": video.images[:, :rows], "masks": video.masks[:, :rows]})


def test_a_body_the_frame_cuts_off_is_as_near_its_masks_as_a_whole_one() -> None:
    """The frames cut at the shins (the sample's feet below the image): the same body on the same poses
    stays on the cut masks (the unseen feet past the lower edge cost nothing, and the mask's cut along
    that edge is not its outline), while a frame whose mask does not reach the edge still charges a point
    for every pixel it lies past the image."""
    video = load_people_snapshot(SAMPLE, FrameRange(0, 59, 10), downscale=1)
    template = load_body_template("anny", phenotype=video.subject["phenotype"])
    lowest_row = max(int(torch.nonzero(mask.any(dim=1)).max()) for mask in video.masks)
    cut = _cut_off_below(video, lowest_row - 25)
    posed = skin_points(template.vertices, template.weights, forward_kinematics(video.body_pose, template.rest_joints, video.transl))
    whole = silhouette_loss(posed, silhouettes(video, torch.arange(len(video)), 96, 200), huber=2.0)
    data = silhouettes(cut, torch.arange(len(cut)), 96, 200)
    assert bool(data.cut[:, 1].all()) and not bool(data.cut[:, [0, 2, 3]].any())
    # a contour pixel on the cut row is the side of a leg: a pixel beside or above it is not the person's
    background = torch.nn.functional.pad(data.outside[:, 0] > 0, (1, 1, 1, 0), value=True)
    for frame, pixels in enumerate(data.contours.long()):
        for x, y in pixels[pixels[:, 1] == data.camera.height - 1].tolist():
            assert bool(background[frame, y : y + 2, x : x + 3].any())
    on_cut_masks = silhouette_loss(posed, data, huber=2.0)
    assert float(on_cut_masks.max()) < 0.1 and float(on_cut_masks.mean()) < 1.5 * float(whole.mean()) + 0.01
    # the same points over masks that end above the edge: everything past it lies outside the person
    data.cut[:] = False
    assert bool((silhouette_loss(posed, data, huber=2.0) > 10 * on_cut_masks).all())
