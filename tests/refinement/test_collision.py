"""Body capsules: segment distances against brute force, the sample motions free of intersections, limbs pushed
into the body caught, and the penalty's gradient against finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from avatarperfect_cli.body import SMPL_JOINT_NAMES, load_body_template
from avatarperfect_cli.refinement.collision import PARTS, BodyCapsules, segment_distances
from avatarperfect_cli.refinement.pose_prior import BuiltinPosePrior
from avatarperfect_cli.sample import motions

JOINT = {name: index for index, name in enumerate(SMPL_JOINT_NAMES)}
GROUP = {part.name: part.group for part in PARTS}


@pytest.fixture(scope="module")
def capsules() -> BodyCapsules:
    template = load_body_template("anny")
    return BodyCapsules.from_points(template.vertices, template.weights, template.rest_joints)


def _brute_force_distance(
    a0: torch.Tensor, a1: torch.Tensor, b0: torch.Tensor, b1: torch.Tensor, samples: int
) -> float:
    s = torch.linspace(0.0, 1.0, samples, dtype=torch.float64)[:, None]
    return float(torch.cdist(a0 + s * (a1 - a0), b0 + s * (b1 - b0)).min())


def test_segment_distances_match_dense_sampling() -> None:
    generator = torch.Generator().manual_seed(0)
    a0, a1, b0, b1 = torch.randn(4, 100, 3, generator=generator, dtype=torch.float64).unbind(0)
    direction = torch.randn(20, 3, generator=generator, dtype=torch.float64)
    # special cases: parallel (overlapping, disjoint, anti-parallel), collinear, crossing, point-like segments
    a0, a1 = a0.clone(), a1.clone()
    stretch = torch.linspace(-2, 2, 20, dtype=torch.float64)[:, None]  # negative: anti-parallel
    b0[:20] = a0[:20] + 0.3 * a1[:20]
    b1[:20] = b0[:20] + direction * stretch
    a1[:20] = a0[:20] + direction
    b0[20:25], b1[20:25] = a0[20:25] + 2.0 * (a1[20:25] - a0[20:25]), a0[20:25] + 3.0 * (a1[20:25] - a0[20:25])
    b0[25:30] = 0.5 * (a0[25:30] + a1[25:30]) - b1[25:30]
    b1[25:30] = 0.5 * (a0[25:30] + a1[25:30]) + b1[25:30]  # crossing at a's middle
    a1[30:35] = a0[30:35]
    b1[35:40] = b0[35:40]
    a1[40:45], b1[40:45] = a0[40:45], b0[40:45]
    ours = segment_distances(a0, a1, b0, b1)
    assert ours.shape == (100,)
    samples = 1001
    for i in range(100):
        brute = _brute_force_distance(a0[i], a1[i], b0[i], b1[i], samples)
        step = max(float((a1[i] - a0[i]).norm()), float((b1[i] - b0[i]).norm())) / (samples - 1)
        assert float(ours[i]) <= brute + 1e-8, i
        assert brute - float(ours[i]) <= step + 1e-9, i
    assert torch.allclose(ours[25:30], torch.zeros(5, dtype=torch.float64), atol=1e-8)


def test_capsules_cover_the_body_conservatively(capsules: BodyCapsules) -> None:
    names = set(capsules.names)
    assert names == {part.name for part in PARTS}
    assert ((capsules.radii > 0.01) & (capsules.radii < 0.15)).all()
    pairs = {frozenset((capsules.names[i], capsules.names[j])) for i, j in capsules.pairs.tolist()}
    assert frozenset(("chest", "left_forearm")) in pairs and frozenset(("left_shin", "right_shin")) in pairs
    # attachments and parts of one limb may touch
    for allowed in (("left_upper_arm", "left_collar"), ("left_thigh", "pelvis"), ("left_forearm", "left_upper_arm"),
                    ("chest", "head"), ("left_shin", "left_foot")):  # fmt: skip
        assert frozenset(allowed) not in pairs


def test_a_part_without_points_is_left_out() -> None:
    template = load_body_template("anny")
    weights = template.weights.clone()
    weights[:, JOINT["left_collar"]] = 0.0
    capsules = BodyCapsules.from_points(template.vertices, weights, template.rest_joints)
    assert "left_collar" not in capsules.names and "right_collar" in capsules.names
    assert capsules.pairs.max() < len(capsules.names)


def test_rest_pose_and_sample_motions_do_not_intersect(capsules: BodyCapsules) -> None:
    poses = [torch.zeros(1, 24, 3, dtype=torch.float64), torch.as_tensor(motions.turntable(100).body_pose)]
    for make in (motions.walk, motions.raise_arms, motions.legs_apart, motions.squat):
        poses.append(torch.as_tensor(make(40).body_pose))
    for pose in poses:
        assert capsules.intersecting_pairs(pose[0]) == [] and capsules.intersecting_pairs(pose[-1]) == []
    everything = torch.cat(poses)
    depths = capsules.pair_depths(everything)  # every frame at once: what intersecting_pairs tests one by one
    assert depths.shape == (len(everything), len(capsules.pairs)) and depths.max() <= 0.01
    assert (capsules.penetration(everything) < 1e-4).all()


def _arm_into_chest() -> torch.Tensor:
    """The left arm swung forwards and across, through the chest."""
    pose = torch.zeros(24, 3, dtype=torch.float64)
    pose[JOINT["left_shoulder"], 1] = math.radians(-160.0)
    return pose


def test_an_arm_through_the_chest_is_caught(capsules: BodyCapsules) -> None:
    found = capsules.intersecting_pairs(_arm_into_chest())
    assert ("chest", "left_upper_arm") in [(a, b) for a, b, _ in found]
    assert all({GROUP[a], GROUP[b]} == {"torso", "left_arm"} for a, b, _ in found)
    depths = [depth for _, _, depth in found]
    assert depths == sorted(depths, reverse=True) and depths[0] > 0.02
    # the same swing short of the chest (arm straight forwards) is fine
    forwards = torch.zeros(24, 3, dtype=torch.float64)
    forwards[JOINT["left_shoulder"], 1] = math.radians(-90.0)
    assert capsules.intersecting_pairs(forwards) == []


def test_crossed_legs_are_caught(capsules: BodyCapsules) -> None:
    pose = torch.zeros(24, 3, dtype=torch.float64)
    pose[JOINT["left_hip"], 2], pose[JOINT["right_hip"], 2] = math.radians(-20.0), math.radians(20.0)
    found = capsules.intersecting_pairs(pose)
    assert ("left_shin", "right_shin") in [(a, b) for a, b, _ in found]
    assert all({GROUP[a], GROUP[b]} == {"left_leg", "right_leg"} for a, b, _ in found)
    # one leg crossed in front of the other (a natural stance) passes
    pose[JOINT["left_hip"], 0], pose[JOINT["right_hip"], 2] = math.radians(-30.0), 0.0
    assert capsules.intersecting_pairs(pose) == []


def test_penetration_matches_the_pairs_and_its_gradient_finite_differences(capsules: BodyCapsules) -> None:
    pose = _arm_into_chest()
    expected = sum(depth**2 for _, _, depth in capsules.intersecting_pairs(pose, tolerance=0.0))
    assert float(capsules.penetration(pose[None])[0]) == pytest.approx(expected, rel=1e-12)
    generator = torch.Generator().manual_seed(1)
    batch = pose + 0.05 * torch.randn(2, 24, 3, generator=generator, dtype=torch.float64)
    assert (capsules.penetration(batch) > 0).all()
    assert torch.autograd.gradcheck(capsules.penetration, (batch.requires_grad_(),))


def test_sampled_poses_mostly_do_not_intersect_and_the_penalty_removes_intersections(capsules: BodyCapsules) -> None:
    reference = torch.as_tensor(motions.turntable(1).body_pose[0])
    prior = BuiltinPosePrior(reference)
    latents = torch.stack([prior.sample_latent(torch.Generator().manual_seed(seed)) for seed in range(50)]).double()
    poses = prior.decode(latents)
    intersecting = [seed for seed, pose in enumerate(poses) if capsules.intersecting_pairs(pose)]
    share = len(intersecting) / len(poses)
    print(f"sampled builtin poses with intersecting parts: {share:.0%} ({len(intersecting)} of {len(poses)})")
    assert 0 < len(intersecting) and share < 0.5
    for seed in intersecting[:3]:
        z = latents[seed].clone().requires_grad_()
        optimizer = torch.optim.Adam([z], lr=0.1)
        for _ in range(40):
            optimizer.zero_grad()
            capsules.penetration(prior.decode(z[None])).sum().backward()
            optimizer.step()
        with torch.no_grad():
            assert capsules.intersecting_pairs(prior.decode(z[None])[0]) == [], seed
            assert (z - latents[seed]).norm() < 5.0  # a nearby pose, not a different one


def test_penetration_accepts_float32_and_agrees_with_float64(capsules: BodyCapsules) -> None:
    pose = _arm_into_chest()[None]
    assert torch.allclose(capsules.penetration(pose.float()).double(), capsules.penetration(pose), rtol=1e-4)
    walk = torch.as_tensor(np.asarray(motions.walk(8).body_pose), dtype=torch.float32)
    assert capsules.penetration(walk).dtype == torch.float32
