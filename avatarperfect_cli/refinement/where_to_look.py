"""Where a person should look first: poses that open what a video of someone standing or turning hides (the
armpits, the crotch, the inner arms), how much each Gaussian such poses show, and per body region the share
of what they show that the video barely saw."""

from __future__ import annotations

import math

import numpy as np
import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.body.regions import BODY_REGIONS, body_regions
from avatarperfect_cli.render import Camera, look_at, rasterization
from avatarperfect_cli.render.camera import framing_distance
from avatarperfect_cli.refinement.suggest import exposure_relevance
from avatarperfect_cli.refinement.visibility import barely_seen
from avatarperfect_cli.sample.motions import legs_apart, raise_arms, walk

EXPOSURE_SIZE = 128  # pixels per side of the exposure renders
EXPOSURE_AZIMUTHS = 8  # views around the body per revealing pose


def revealing_poses() -> dict[str, torch.Tensor]:
    """Name -> (24, 3) float32 SMPL axis-angle body pose facing +Z: the T-pose and three poses that open what
    a standing or turning video hides."""
    poses = {
        "T-pose": np.zeros((24, 3)),
        "arms raised": raise_arms(6).body_pose[3],  # overhead, palms forward: armpits and inner arms face the front
        "legs apart": legs_apart(4).body_pose[-1],  # each leg 35 degrees out, arms out with the palms forward
        "walking step": walk(8).body_pose[2],  # the left leg forward, the right behind
    }
    return {name: torch.from_numpy(pose).float() for name, pose in poses.items()}


def framed_camera(points: torch.Tensor, direction: tuple[float, ...], up: tuple[float, ...], size: int) -> Camera:
    """A size x size camera looking at the middle of `points` (N, 3) from `direction` (towards the camera),
    `up` up in the image, far enough that every point fits in 92% of the image."""
    center = 0.5 * (points.min(dim=0).values + points.max(dim=0).values)
    focal = 2.5 * size
    K = torch.tensor([[focal, 0.0, size / 2], [0.0, focal, size / 2], [0.0, 0.0, 1.0]])
    towards = torch.nn.functional.normalize(torch.tensor(direction, dtype=torch.float32), dim=0)
    rotation = look_at(center + towards, center, torch.tensor(up))[:3, :3]
    distance = float(framing_distance(points - center, rotation, K, size, size, fill=0.92))
    return Camera(K, look_at(center + distance * towards, center, torch.tensor(up)), size, size)


def revealing_exposure(avatar: Avatar, size: int = EXPOSURE_SIZE, azimuths: int = EXPOSURE_AZIMUTHS) -> torch.Tensor:
    """E: (N,) float64 mean visibility (pixels at `size`) of every Gaussian over the `revealing_poses`, each
    seen from `azimuths` directions around it at body height; near zero inside the body (the mouth, the
    eyes' backs, Gaussians under the surface), which no pose shows."""
    total = torch.zeros(len(avatar), dtype=torch.float64, device=avatar.device)
    views = 0
    with torch.no_grad():
        for pose in revealing_poses().values():
            means, quats = avatar.pose(pose, torch.zeros(3))
            for k in range(azimuths):
                angle = 2.0 * math.pi * k / azimuths
                camera = framed_camera(means.cpu(), (math.sin(angle), 0.0, math.cos(angle)), (0.0, 1.0, 0.0), size)
                no_colours = means.new_zeros(len(means), 1)
                out = rasterization(means, quats, avatar.scales, avatar.opacities, no_colours, camera.to(avatar.device))
                total += out.visibility.double()
                views += 1
    return (total / views).cpu()


def barely_seen_by_region(avatar: Avatar, visibility: torch.Tensor, exposure: torch.Tensor) -> list[tuple[str, float, int]]:
    """(region, share barely seen, Gaussian count) for every body region (`body.regions`) that has Gaussians,
    the largest share first. The share counts each Gaussian by how much the revealing poses show it
    (`exposure` (N,), weighted as suggest weighs, `exposure_relevance`), so what no pose shows does not count;
    visibility: V (N,)."""
    with torch.no_grad():
        regions = body_regions(avatar.params["means"], avatar.skin_weights, avatar.rest_joints).cpu()
    relevance = exposure_relevance(exposure.cpu().double())
    barely = barely_seen(visibility.cpu()).double()
    shown = torch.zeros(len(BODY_REGIONS), dtype=torch.float64).index_add_(0, regions, relevance)
    shown_barely = torch.zeros(len(BODY_REGIONS), dtype=torch.float64).index_add_(0, regions, relevance * barely)
    counts = torch.bincount(regions, minlength=len(BODY_REGIONS))
    shares = [
        (name, float(shown_barely[index] / shown[index]) if shown[index] > 0 else 0.0, int(counts[index]))
        for index, name in enumerate(BODY_REGIONS)
        if counts[index] > 0
    ]
    return sorted(shares, key=lambda entry: -entry[1])
