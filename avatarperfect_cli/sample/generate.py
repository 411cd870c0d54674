"""The synthetic sample subject: a textured anny body, posed by our skeleton, rendered as two videos.

`make_sample` writes OUT/train (an A-pose turntable, like the iPER videos the paper trains on) and
OUT/test (held-out motions seen from turning views), both in the People-Snapshot layout. The ground
truth is exact: the same linear blend skinning the avatar uses, rendered by the mesh rasterizer.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from rich.progress import Progress

from avatarperfect_cli.body import load_body_template
from avatarperfect_cli.body.anny_model import full_phenotype
from avatarperfect_cli.body.base import BodyTemplate
from avatarperfect_cli.datasets.people_snapshot import write_people_snapshot
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.io.motion import write_motion
from avatarperfect_cli.render.camera import Camera, look_at
from avatarperfect_cli.sample import motions
from avatarperfect_cli.sample.subject import SyntheticSubject, frame_pixels, skin_template
from avatarperfect_cli.sample.texture import HIDDEN_REGIONS, REGION, REGIONS, get_preset

CAMERA_DISTANCE = 2.6  # metres from the camera to the vertical axis the body turns about
FRAME_MARGIN = 1.1  # the image spans this many times the widest view angle any frame needs
MIN_RESOLUTION = 16  # pixels; below this the body is a few pixels tall


@dataclass
class RenderedVideo:
    """images: (T, H, W, 3) uint8 on white; masks: (T, H, W) bool; region_pixels: (T, len(REGIONS))
    int64, how many pixels of each frame show each texture region (pixels with coverage >= 0.5)."""

    images: np.ndarray
    masks: np.ndarray
    region_pixels: np.ndarray


def make_sample(
    out_dir: Path,
    preset: str = "default",
    resolution: int = 512,
    seed: int = 0,
    train_frames: int = 100,
    test_frames: int = 30,
    phenotype: dict[str, float] | None = None,
) -> None:
    """Write the synthetic subject's training video to out_dir/train and its test video to out_dir/test.

    preset: a name from texture.PRESETS (body shape and clothes); resolution: square image side in pixels;
    phenotype: another anny body for the preset's clothes (names in anny_model.PHENOTYPES, missing ones 0.5).
    Both videos share one fixed camera that keeps every frame's body in view. The same arguments give
    byte-identical files. Raises AvatarPerfectError for an unknown preset or a size below the minimum.
    """
    if resolution < MIN_RESOLUTION or train_frames < 1 or test_frames < 1:
        raise AvatarPerfectError(
            f"make-sample needs a resolution of at least {MIN_RESOLUTION} px and at least one frame per video, "
            f"got {resolution} px, {train_frames} training and {test_frames} test frames"
        )
    body = full_phenotype(phenotype) if phenotype else get_preset(preset).phenotype
    synthetic = SyntheticSubject.create(preset, seed, body)
    posed = {
        "train": posed_vertices(synthetic.template, motions.turntable(train_frames, seed)),
        "test": posed_vertices(synthetic.template, motions.held_out_motion(test_frames)),
    }
    camera = fit_camera(np.concatenate([vertices.reshape(-1, 3) for vertices, _ in posed.values()]), resolution)
    with Progress(transient=True) as progress:
        task = progress.add_task("rendering frames", total=train_frames + test_frames)
        rendered = {
            split: render_video(synthetic, camera, vertices, lambda: progress.advance(task))
            for split, (vertices, _) in posed.items()
        }
    for split, video in rendered.items():
        motion = posed[split][1]
        subject = {
            "body_model": "anny",
            "phenotype": body,
            "preset": preset,
            "seed": seed,
            "split": split,
            "hidden_region_fraction": hidden_region_fractions(video.region_pixels, resolution * resolution),
        }
        write_people_snapshot(
            Path(out_dir) / split, video.images, video.masks, motion.body_pose, motion.transl, camera, subject=subject
        )


def fit_camera(points: np.ndarray, resolution: int) -> Camera:
    """The fixed square camera: CAMERA_DISTANCE in front of the vertical axis (+Z), looking horizontally
    (-Z) from the height that needs the narrowest view, zoomed so `points` (N, 3) fill 1 / FRAME_MARGIN
    of the image."""
    depth = CAMERA_DISTANCE - points[:, 2]
    height = points[:, 1]

    def vertical_spread(centre: float) -> float:
        return float((np.abs(height - centre) / depth).max())

    # The spread is convex in the camera height (a maximum of |linear| terms): golden-section search.
    low, high = float(height.min()), float(height.max())
    ratio = (np.sqrt(5.0) - 1.0) / 2.0
    for _ in range(60):
        a, b = high - ratio * (high - low), low + ratio * (high - low)
        if vertical_spread(a) <= vertical_spread(b):
            high = b
        else:
            low = a
    centre = 0.5 * (low + high)
    spread = max(vertical_spread(centre), float((np.abs(points[:, 0]) / depth).max()))
    focal = resolution / 2 / (FRAME_MARGIN * spread)
    K = torch.tensor([[focal, 0.0, resolution / 2], [0.0, focal, resolution / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    eye = torch.tensor([0.0, centre, CAMERA_DISTANCE], dtype=torch.float64)
    target = torch.tensor([0.0, centre, 0.0], dtype=torch.float64)
    view = look_at(eye, target, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    return Camera(K, view, resolution, resolution)


def posed_vertices(template: BodyTemplate, motion: motions.Motion) -> tuple[np.ndarray, motions.Motion]:
    """Skin the template by `motion` and lift every frame so its lowest vertex stands on the rest pose's
    floor. Returns vertices (T, V, 3) float64 metres and the motion with the grounded translations."""
    vertices = template.vertices.double()
    posed = skin_template(template, torch.as_tensor(motion.body_pose), torch.as_tensor(motion.transl))
    lift = vertices[:, 1].min() - posed[:, :, 1].min(dim=1).values
    posed[:, :, 1] += lift[:, None]
    grounded = motion.transl.copy()
    grounded[:, 1] += lift.numpy()
    return posed.numpy(), motions.Motion(motion.body_pose, grounded)


def render_video(
    subject: SyntheticSubject,
    camera: Camera,
    posed: np.ndarray,
    on_frame: Callable[[], None] = lambda: None,
) -> RenderedVideo:
    """Render the subject's posed vertices (T, V, 3); `on_frame` is called after each frame (progress)."""
    count, size = len(posed), (camera.height, camera.width)
    images = np.empty((count, *size, 3), np.uint8)
    masks = np.empty((count, *size), bool)
    region_pixels = np.empty((count, len(REGIONS)), np.int64)
    for index, vertices in enumerate(posed):
        frame = subject.render_vertices(vertices, camera)
        images[index], masks[index] = frame_pixels(frame)
        region_pixels[index] = np.bincount(frame.labels[frame.labels >= 0], minlength=len(REGIONS))
        on_frame()
    return RenderedVideo(images, masks, region_pixels)


def hidden_region_fractions(region_pixels: np.ndarray, image_pixels: int) -> dict[str, float]:
    """Share of a video's foreground pixels, and of all its pixels, that show the hidden regions
    (inner arms, armpits, crotch), overall and per region. region_pixels: (T, len(REGIONS)) counts
    from `render_video`; image_pixels: pixels per frame."""
    totals = region_pixels.sum(axis=0)
    foreground = max(int(totals.sum()), 1)
    hidden = {name: int(totals[REGION[name]]) for name in HIDDEN_REGIONS}
    return {
        "of_foreground": sum(hidden.values()) / foreground,
        "of_image": sum(hidden.values()) / (image_pixels * len(region_pixels)),
        **{name: count / foreground for name, count in hidden.items()},
    }


EXAMPLE_MOTIONS = {"walk": motions.walk, "raise_arms": motions.raise_arms, "squat": motions.squat}


def write_example_motions(out_dir: Path, frames: int = 60, preset: str = "default") -> list[Path]:
    """Write examples/motions-style files OUT/{walk,raise_arms,squat}.npz, facing the camera and
    grounded on `preset`'s body. Returns the paths."""
    template = load_body_template("anny", phenotype=get_preset(preset).phenotype)
    paths = []
    for name, make in EXAMPLE_MOTIONS.items():
        _, grounded = posed_vertices(template, make(frames))
        path = Path(out_dir) / f"{name}.npz"
        write_motion(path, torch.as_tensor(grounded.body_pose), torch.as_tensor(grounded.transl))
        paths.append(path)
    return paths

