"""The subject's body from the video's masks: anny's phenotype, a skeleton correction and the translation
offset, fitted before any Gaussian is trained.

The template is posed by the video's poses and projected into the camera; its outline is compared with the
person masks by the silhouette distances of `training/silhouette.py` (pixels at the fit's resolution).
They are differentiable in the template through anny's torch forward pass, so Adam fits:
    phenotype      anny's six values, through a sigmoid (they stay in (0, 1)), pulled toward the middle by
                   a weak prior so that size is not traded for distance where the camera is uncertain;
    bone offsets   a change of each bone's offset from its parent joint (24, 3), left and right mirrored,
                   pulled toward zero: limbs and shoulders land where the masks show them in every pose;
    offset         a translation in the image plane added to every frame (along the viewing direction a
                   silhouette only tells the body's size).
The root joint of a posed body lands at its rest position plus the frame's translation, and anny's rest
root moves with the phenotype (its feet stay put: a taller body's pelvis is higher). So the translation
follows the root: a phenotype that moves the rest root by d moves every frame's translation by -d, and
the body grows and shrinks about the place where the video's translations put its pelvis instead of
about its feet, which the offset would otherwise have to chase (tens of centimetres for a tall body).
The fit starts from a few phenotypes (the middle, a more male, a more female and an older body) and continues
the best.
With estimated poses (`poses` given) the starts are compared only after each has also fitted the compared
frames' poses for a few steps (on a copy): on poses 3 degrees off the start phase's distance is mostly the
poses' error (about 1.6 px against 0.1 px once they are corrected), and the body that best fits the wrong
poses can be the wrong body. The best start then continues over every frame with each frame's pose fitted
at the same time (`pose_fit.PoseOffsets`: smooth along the video, near the given pose, averaging to zero
over the video): a pose estimator's errors differ from frame to frame and the body is the same in all, so
what every frame shares goes to the body and the offset, and the fit cannot bend a bone to absorb one
frame's wrong joint angle, which fitting body and poses in turn does.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from avatarperfect_cli.body import BodyTemplate, forward_kinematics, skin_points
from avatarperfect_cli.body.anny_model import PHENOTYPES, anny_shape, joint_weights
from avatarperfect_cli.body.base import SMPL_MIRROR, joint_displacements
from avatarperfect_cli.datasets import VideoDataset
from avatarperfect_cli.datasets.people_snapshot import downscaled_camera
from avatarperfect_cli.render import Camera
from avatarperfect_cli.render.mesh_raster import mesh_coverage
from avatarperfect_cli.training.pose_fit import PoseFitConfig, PoseOffsets
from avatarperfect_cli.training.silhouette import Silhouettes, silhouette_loss, silhouettes, surface_points

# Phenotype values are stored rounded to this many decimals, so a recorded body rebuilds the same template.
PHENOTYPE_DECIMALS = 4


@dataclass
class BodyFitConfig:
    """Settings of the body fit.

    frames:          video frames compared (evenly spaced over the video)
    resolution:      longest side of the compared masks, pixels
    points:          template vertices posed and projected (drawn by surface area, fixed)
    contour_pixels:  mask-contour pixels per frame in the coverage term (drawn, fixed)
    starts:          starting phenotypes (missing values 0.5); each runs `start_steps`, the best goes on
    start_steps:     steps on phenotype and offset from each start
    pick_steps:      with estimated poses, steps of each start (a copy) with the compared frames' poses fitted
                     too before the starts are compared by their silhouette distance
    shape_steps:     steps of the best start with the skeleton correction added
    shape_steps_with_poses: the same with estimated poses, where every frame's pose is fitted too and the body
                     converges slower (the custom subject's noisy video, docs/body-fit.md: 200 steps left its rest
                     joints 0.82 cm from the truth, 400 steps 0.53 cm; with the poses given, 400 steps gain 0.02-0.3 cm)
    relinearise_every: steps between anny forward passes (the template is linear in the phenotype between)
    phenotype_rate:  Adam step on the phenotype logits; offset_rate, bone_rate: metres
    phenotype_prior: loss (pixels) of a value 0.5 from the middle, growing with its square
    bone_prior:      loss (pixels) of a 1 cm bone offset, growing with its square
    huber:           pixels beyond which a distance counts linearly
    """

    frames: int = 24
    resolution: int = 256
    points: int = 5000
    contour_pixels: int = 400
    starts: tuple[dict[str, float], ...] = field(default_factory=lambda: ({}, {"gender": 0.15}, {"gender": 0.85}, {"age": 0.85}))
    start_steps: int = 80
    pick_steps: int = 30
    shape_steps: int = 200
    shape_steps_with_poses: int = 400
    phenotype_rate: float = 0.04
    offset_rate: float = 0.003
    bone_rate: float = 0.002
    relinearise_every: int = 20
    phenotype_prior: float = 0.02
    bone_prior: float = 0.002
    huber: float = 2.0

    def steps(self, starts: int, with_poses: bool) -> int:
        """Optimisation steps of a fit from `starts` starts (the count `fit_body`'s on_step sees)."""
        picking = self.pick_steps if with_poses and starts > 1 else 0
        return starts * (self.start_steps + picking) + (self.shape_steps_with_poses if with_poses else self.shape_steps)


@dataclass
class BodyFit:
    """phenotype: anny's six values; bone_offsets: (24, 3) metres, canonical frame (`BodyTemplate.with_bone_offsets`);
    transl_offset: (3,) metres, world frame, added to every frame's transl; loss: the final silhouette loss,
    pixels; start_loss: the same for the starting body at the starting offset; start_losses: each start's
    loss when the starts were compared (`BodyFitConfig.pick_steps`); body_pose (T, 24, 3) radians and transl
    (T, 3) metres (the offset included): the video's poses fitted with the body, when asked for."""

    phenotype: dict[str, float]
    bone_offsets: torch.Tensor
    transl_offset: torch.Tensor
    loss: float
    start_loss: float
    start_losses: tuple[float, ...] = ()
    body_pose: torch.Tensor | None = None
    transl: torch.Tensor | None = None


def _mirrored(bone_offsets: torch.Tensor) -> torch.Tensor:
    """(24, 3) offsets made left-right symmetric (+X is the body's left); the spine's have no sideways part."""
    flipped = bone_offsets[list(SMPL_MIRROR)] * torch.tensor([-1.0, 1.0, 1.0])
    symmetric = 0.5 * (bone_offsets + flipped)
    return torch.cat([torch.zeros_like(symmetric[:1]), symmetric[1:]])


class _BodyShape(torch.nn.Module):
    """The fitted quantities: phenotype logits (6,), bone offsets (24, 3) metres, image-plane offset (2,) metres."""

    def __init__(self, phenotype: dict[str, float]) -> None:
        super().__init__()
        values = torch.tensor([min(max(phenotype.get(name, 0.5), 0.02), 0.98) for name in PHENOTYPES])
        self.logits = torch.nn.Parameter(torch.log(values / (1.0 - values)))
        self.bones = torch.nn.Parameter(torch.zeros(24, 3))
        self.image_offset = torch.nn.Parameter(torch.zeros(2))

    def phenotype(self) -> torch.Tensor:
        return torch.sigmoid(self.logits)

    def bone_offsets(self) -> torch.Tensor:
        return _mirrored(self.bones)


class _LinearisedAnny:
    """anny's T-pose points and rest joints near one phenotype, linear in the phenotype (a forward pass costs
    about 40 ms, so the fit re-linearises every few steps instead of running one per step).

    points: indices of the template vertices kept; step: phenotype difference of the finite differences.
    """

    def __init__(self, model: object, points: torch.Tensor, step: float = 0.02) -> None:
        self.model, self.points, self.step = model, points, step
        self.centre = torch.full((len(PHENOTYPES),), math.nan)

    def linearise(self, phenotype: torch.Tensor) -> None:
        """Evaluate anny at `phenotype` (6,) and at a step along each value (toward the middle)."""
        centre = phenotype.detach().double()
        deltas = torch.full_like(centre, self.step)
        deltas[centre >= 0.5] = -self.step
        with torch.no_grad():  # one batched forward pass: the centre, then a step along each value
            vertices, joints = anny_shape(self.model, torch.cat([centre[None], centre + torch.diag(deltas)]))
        points = vertices[:, self.points]
        self.centre = centre.float()
        self.base_points, self.base_joints = points[0].float(), joints[0].float()
        self.point_slopes = ((points[1:] - points[0]) / deltas[:, None, None]).float()
        self.joint_slopes = ((joints[1:] - joints[0]) / deltas[:, None, None]).float()

    def __call__(self, phenotype: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Points (P, 3) and rest joints (24, 3) at `phenotype` (6,), SMPL frame, metres."""
        change = phenotype - self.centre
        points = self.base_points + torch.einsum("k,kpc->pc", change, self.point_slopes)
        return points, self.base_joints + torch.einsum("k,kjc->jc", change, self.joint_slopes)


class _FixedShape:
    """A template whose shape is given (SMPL with the dataset's betas): the phenotype changes nothing."""

    def __init__(self, template: BodyTemplate, points: torch.Tensor) -> None:
        self.points, self.joints = template.vertices[points].float(), template.rest_joints.float()

    def linearise(self, phenotype: torch.Tensor) -> None:
        pass

    def __call__(self, phenotype: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.points, self.joints


@dataclass
class _Compared:
    """What one phase of the fit compares: the frames' silhouettes, the body's linearised points and their
    skinning weights (P, 24), and the per-frame pose corrections (None: the given poses are kept)."""

    data: Silhouettes
    shape_near: _LinearisedAnny | _FixedShape
    weights: torch.Tensor
    poses: PoseOffsets | None = None


def fit_body(
    video: VideoDataset,
    initial_offset: torch.Tensor,
    config: BodyFitConfig | None = None,
    *,
    anny_model: object | None = None,
    template: BodyTemplate | None = None,
    poses: PoseFitConfig | None = None,
    on_step: Callable[[], None] | None = None,
) -> BodyFit:
    """Fit the body to the video's masks: anny's phenotype (with `anny_model`, a loaded `anny.Anny`) or the
    given `template`'s shape as it is, plus the skeleton correction and the image-plane offset; with `poses`
    also every frame's pose, together with the body (the shape phase then runs over every frame, at the pose
    fit's resolution and point counts).

    initial_offset: (3,) metres, world frame, where the start body already lands on the masks
    (`template_offset.fit_transl_offset`), kept along the viewing direction; on_step: called after every
    optimisation step (progress). With a given template the returned phenotype is empty.
    """
    config = config or BodyFitConfig()
    frames = torch.linspace(0, len(video) - 1, min(config.frames, len(video))).round().long().unique()
    if anny_model is not None:
        with torch.no_grad():
            start_vertices, start_joints = anny_shape(anny_model, torch.full((len(PHENOTYPES),), 0.5, dtype=torch.float64))
        start_vertices, start_root = start_vertices.float(), start_joints[0].float()
        faces, weights = anny_model.faces.long(), joint_weights(anny_model).float()
        starts = config.starts
    elif template is not None:
        start_vertices, faces, weights = template.vertices.float(), template.faces, template.weights.float()
        start_root, starts = template.rest_joints[0].float(), ({},)
    else:
        raise ValueError("fit_body needs anny_model or template")

    def compared(data: Silhouettes, points: int, offsets: PoseOffsets | None = None) -> _Compared:
        chosen = surface_points(start_vertices, faces, points)
        near = _LinearisedAnny(anny_model, chosen) if anny_model is not None else _FixedShape(template, chosen)
        return _Compared(data, near, weights[chosen], offsets)

    subset = compared(silhouettes(video, frames, config.resolution, config.contour_pixels), config.points)
    if poses is None:
        whole = subset
    else:
        every = silhouettes(video, torch.arange(len(video)), poses.resolution, poses.contour_pixels)
        whole = compared(every, poses.points, PoseOffsets(video.frame_ids, poses, zero_mean=True))
    axes = subset.data.camera.world_to_camera[:2, :3].float()  # the camera's right and down axes, world frame

    def offset_of(shape: _BodyShape, root: torch.Tensor) -> torch.Tensor:
        """(3,) metres added to every frame's transl for the body whose rest root is `root` (3,)."""
        return initial_offset + (start_root - root) + shape.image_offset @ axes

    def loss_of(shape: _BodyShape, on: _Compared, with_bones: bool) -> tuple[torch.Tensor, torch.Tensor]:
        points, joints = on.shape_near(shape.phenotype())
        body_pose, transl = on.data.body_pose, on.data.transl + offset_of(shape, joints[0])
        if with_bones:
            displacements = joint_displacements(shape.bone_offsets())
            points = points + on.weights @ displacements
            joints = joints + displacements
        if on.poses is not None:
            body_pose, transl = body_pose + on.poses.pose, transl + on.poses.transl
        posed = skin_points(points, on.weights, forward_kinematics(body_pose, joints, transl))
        fit = silhouette_loss(posed, on.data, config.huber).mean()
        prior = config.phenotype_prior * ((shape.phenotype() - 0.5) / 0.5).square().sum()
        if with_bones:
            prior = prior + config.bone_prior * (shape.bone_offsets() / 0.01).square().sum()
        if on.poses is not None:
            prior = prior + on.poses.penalty(posed)
        return fit + prior, fit

    def optimise(shape: _BodyShape, on: _Compared, steps: int, with_bones: bool) -> float:
        groups = [
            {"params": [shape.logits], "lr": config.phenotype_rate},
            {"params": [shape.image_offset], "lr": config.offset_rate},
        ]
        if with_bones:
            groups.append({"params": [shape.bones], "lr": config.bone_rate})
        if on.poses is not None:
            groups.extend(on.poses.param_groups())
        optimizer = torch.optim.Adam(groups)
        for step in range(steps):
            if step % config.relinearise_every == 0:
                on.shape_near.linearise(shape.phenotype())
            optimizer.zero_grad(set_to_none=True)
            loss_of(shape, on, with_bones)[0].backward()
            optimizer.step()
            if on_step is not None:
                on_step()
        on.shape_near.linearise(shape.phenotype())
        with torch.no_grad():
            return float(loss_of(shape, on, with_bones)[0])

    def corrected_distance(shape: _BodyShape) -> float:
        """The silhouette distance of a copy of `shape` after `pick_steps` with the subset's poses fitted too."""
        trial, offsets = copy.deepcopy(shape), PoseOffsets(video.frame_ids[frames], poses, zero_mean=True)
        on = _Compared(subset.data, subset.shape_near, subset.weights, offsets)
        optimise(trial, on, config.pick_steps, False)
        with torch.no_grad():
            return float(loss_of(trial, on, False)[1])

    with torch.no_grad():
        subset.shape_near.linearise(torch.full((len(PHENOTYPES),), 0.5))
        start_loss = float(loss_of(_BodyShape({}), subset, False)[1])
    candidates = []
    for start in starts:
        shape = _BodyShape(start)
        loss = optimise(shape, subset, config.start_steps, False)
        candidates.append((corrected_distance(shape) if poses is not None and len(starts) > 1 else loss, shape))
    best = min(candidates, key=lambda candidate: candidate[0])[1]
    optimise(best, whole, config.shape_steps if poses is None else config.shape_steps_with_poses, True)
    with torch.no_grad():
        loss = float(loss_of(best, whole, True)[1])
        phenotype = {name: round(float(value), PHENOTYPE_DECIMALS) for name, value in zip(PHENOTYPES, best.phenotype())}
        phenotype = phenotype if anny_model is not None else {}
        offset = offset_of(best, whole.shape_near(best.phenotype())[1][0]).detach().clone()
    start_losses = tuple(candidate[0] for candidate in candidates)
    result = BodyFit(phenotype, best.bone_offsets().detach().clone(), offset, loss, start_loss, start_losses)
    if whole.poses is not None:
        result.body_pose, result.transl = whole.poses.applied(video.body_pose, video.transl + offset)
    return result


# Colours of the fit picture: mask pixels the body misses, body pixels outside the mask, both.
_MISSED, _OUTSIDE, _BOTH = (1.0, 0.6, 0.1), (0.15, 0.35, 1.0), (0.6, 0.6, 0.6)


def fit_picture(
    video: VideoDataset, bodies: list[tuple[BodyTemplate, torch.Tensor, torch.Tensor]], columns: int = 4, resolution: int = 256
) -> tuple[np.ndarray, list[float]]:
    """A row per body (template, the video's poses (T, 24, 3) and translations (T, 3) for it) over `columns`
    evenly spaced training masks: grey where body and mask agree, orange where the body misses the mask, blue
    where it sticks out; and each body's mean IoU with the masks over those frames. Returns the picture
    (H, W, 3) float in [0, 1] and the IoUs."""
    frames = torch.linspace(0, len(video) - 1, min(columns, len(video))).round().long().unique()
    factor = max(1, round(max(video.camera.width, video.camera.height) / resolution))
    camera = downscaled_camera(video.camera, factor)
    masks = F.interpolate(video.masks[frames].float()[:, None], size=(camera.height, camera.width), mode="area")[:, 0] >= 0.5
    rows, ious = [], []
    for template, body_pose, transl in bodies:
        panels, scores = [], []
        for frame, mask in zip(frames.tolist(), masks):
            body = torch.from_numpy(body_silhouette(template, body_pose[frame], transl[frame], camera) >= 0.5)
            scores.append(float((body & mask).sum()) / max(float((body | mask).sum()), 1.0))
            panel = torch.ones(camera.height, camera.width, 3)
            panel[mask & ~body] = torch.tensor(_MISSED)
            panel[body & ~mask] = torch.tensor(_OUTSIDE)
            panel[body & mask] = torch.tensor(_BOTH)
            panels.append(panel)
        rows.append(torch.cat(panels, dim=1))
        ious.append(sum(scores) / len(scores))
    return torch.cat(rows, dim=0).numpy(), ious


def body_silhouette(template: BodyTemplate, body_pose: torch.Tensor, transl: torch.Tensor, camera: Camera) -> np.ndarray:
    """(H, W) float32 in [0, 1]: how much of each pixel the template's mesh covers, posed by body_pose
    (24, 3) axis-angle and transl (3,) metres (2 x 2 subsamples a pixel)."""
    with torch.no_grad():
        transforms = forward_kinematics(body_pose[None].float(), template.rest_joints.float(), transl[None].float())[0]
        vertices = skin_points(template.vertices.float(), template.weights.float(), transforms)
    return mesh_coverage(vertices.numpy(), template.faces.numpy(), camera)
