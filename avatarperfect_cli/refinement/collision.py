"""Body self-intersection: a capsule model of the body on SMPL's 24-joint skeleton.

Each capsule is a segment carried rigidly by one joint's transform, plus a radius, fitted to the canonical points
(an avatar's Gaussian means or a template's vertices) whose largest skinning weight belongs to the part's joints:
- limbs, neck and collar bones: the segment from the joint to its child joint;
- torso pieces (pelvis, spine1, spine2, spine3): a sideways segment (canonical X) through the points' centroid,
  as the trunk is wider than deep;
- head, hands and feet: a segment along the points' principal axis.
The radius is the median of the points' distances to the segment, shrunk a little; a fitted capsule spans the
points' extent along its axis shrunk alike, and a limb's capsule starts at its joint (its rounded end, not its
segment, reaches the joint). So capsules lie inside the body: touching skin is not a collision, only limbs pushed
into the torso or into each other are. Parts with fewer than `MIN_PART_POINTS` points are left out.

Pairs that may not touch: arms and legs against the torso, left against right arm and leg, arms against legs, and
head and neck against the arms, except adjacent parts (a limb's attachment: the upper arm and its collar bone, the
thigh and the pelvis).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from avatarperfect_cli.body import NUM_JOINTS, SMPL_PARENTS, forward_kinematics
from avatarperfect_cli.errors import AvatarPerfectError

# Radius of a part = RADIUS_SHRINK * this quantile of its points' distances to the part's segment.
RADIUS_QUANTILE = 0.5
RADIUS_SHRINK = 0.85
# The extent of a part's points along a fitted capsule's axis: between these quantiles of their positions.
EXTENT_QUANTILES = (0.02, 0.98)
MIN_PART_POINTS = 10
# Parts whose anchor joints are at most this many edges apart in the kinematic tree may touch.
ATTACHMENT_TREE_DISTANCE = 1
# Segments shorter than this (metres) are treated as points; directions closer to parallel than this
# (squared sine of their angle) as parallel.
_DEGENERATE_LENGTH_SQ = 1e-12
_PARALLEL_SINE_SQ = 1e-10


@dataclass(frozen=True)
class _Part:
    """name; joints: the joints whose dominated points form the part (the first is its anchor in the tree);
    carrier: the joint whose transform moves it; group: torso, head, left_arm, ...; shape: "bone" (segment from the
    anchor to `child`), "lateral" (along canonical X) or "principal" (along the points' principal axis)."""

    name: str
    joints: tuple[int, ...]
    carrier: int
    group: str
    shape: str
    child: int = -1


def _side_parts(side: str, sign: int) -> tuple[_Part, ...]:
    """The arm and leg parts of one side; `sign` 0 for left, 1 for right (SMPL numbers right joints one higher)."""
    return (
        _Part(f"{side}_collar", (13 + sign,), 13 + sign, "torso", "bone", 16 + sign),
        _Part(f"{side}_upper_arm", (16 + sign,), 16 + sign, f"{side}_arm", "bone", 18 + sign),
        _Part(f"{side}_forearm", (18 + sign,), 18 + sign, f"{side}_arm", "bone", 20 + sign),
        _Part(f"{side}_hand", (20 + sign, 22 + sign), 22 + sign, f"{side}_arm", "principal"),
        _Part(f"{side}_thigh", (1 + sign,), 1 + sign, f"{side}_leg", "bone", 4 + sign),
        _Part(f"{side}_shin", (4 + sign,), 4 + sign, f"{side}_leg", "bone", 7 + sign),
        _Part(f"{side}_foot", (7 + sign, 10 + sign), 7 + sign, f"{side}_leg", "principal"),
    )


PARTS: tuple[_Part, ...] = (
    _Part("pelvis", (0,), 0, "torso", "lateral"),
    _Part("lower_torso", (3,), 3, "torso", "lateral"),
    _Part("middle_torso", (6,), 6, "torso", "lateral"),
    _Part("chest", (9,), 9, "torso", "lateral"),
    _Part("neck", (12,), 12, "head", "bone", 15),
    _Part("head", (15,), 15, "head", "principal"),
    *_side_parts("left", 0),
    *_side_parts("right", 1),
)
# Groups whose parts may not touch each other.
FORBIDDEN_CONTACTS: frozenset[frozenset[str]] = frozenset(
    frozenset(pair)
    for pair in (
        ("left_arm", "torso"), ("right_arm", "torso"), ("left_leg", "torso"), ("right_leg", "torso"),
        ("left_arm", "right_arm"), ("left_leg", "right_leg"),
        ("left_arm", "left_leg"), ("left_arm", "right_leg"), ("right_arm", "left_leg"), ("right_arm", "right_leg"),
        ("head", "left_arm"), ("head", "right_arm"),
    )
)  # fmt: skip


def _tree_distance(a: int, b: int) -> int:
    """Edges between joints a and b in SMPL's kinematic tree."""

    def ancestry(joint: int) -> list[int]:
        chain = [joint]
        while SMPL_PARENTS[chain[-1]] >= 0:
            chain.append(SMPL_PARENTS[chain[-1]])
        return chain

    chain_a, chain_b = ancestry(a), ancestry(b)
    common = next(joint for joint in chain_a if joint in chain_b)
    return chain_a.index(common) + chain_b.index(common)


def segment_distances(
    starts_a: torch.Tensor, ends_a: torch.Tensor, starts_b: torch.Tensor, ends_b: torch.Tensor
) -> torch.Tensor:
    """Closest distances between segments a and b: all (..., 3), broadcast, metres -> (...,).

    Minimises |a(s) - b(t)| over s, t in [0, 1] (Ericson, Real-Time Collision Detection, 5.1.9): the unconstrained
    s is clamped, t follows from s and is clamped, and s is recomputed from the clamped t. Parallel segments take
    s = 0 first, which the clamping turns into a closest pair; point-like segments work too. Differentiable.
    """
    dir_a, dir_b, offset = ends_a - starts_a, ends_b - starts_b, starts_a - starts_b
    len_a, len_b = (dir_a * dir_a).sum(-1), (dir_b * dir_b).sum(-1)
    dot_ab, along_a, along_b = (dir_a * dir_b).sum(-1), (dir_a * offset).sum(-1), (dir_b * offset).sum(-1)
    point_a, point_b = len_a < _DEGENERATE_LENGTH_SQ, len_b < _DEGENERATE_LENGTH_SQ
    safe_len_a = torch.where(point_a, torch.ones_like(len_a), len_a)
    safe_len_b = torch.where(point_b, torch.ones_like(len_b), len_b)
    denominator = len_a * len_b - dot_ab * dot_ab
    parallel = denominator <= _PARALLEL_SINE_SQ * len_a * len_b
    safe_denominator = torch.where(parallel, torch.ones_like(denominator), denominator)
    s_free = ((dot_ab * along_b - along_a * len_b) / safe_denominator).clamp(0, 1)
    s = torch.where(parallel, torch.zeros_like(len_a), s_free)
    s = torch.where(point_a, torch.zeros_like(s), s)
    t_free = torch.where(point_b, torch.zeros_like(s), (dot_ab * s + along_b) / safe_len_b)
    t = t_free.clamp(0, 1)
    # where t was clamped (or b is a point), the best s for that t: minimise |offset + s dir_a - t dir_b| over s
    s_for_t = ((t * dot_ab - along_a) / safe_len_a).clamp(0, 1)
    s = torch.where(((t_free != t) | point_b) & ~point_a, s_for_t, s)
    gap = offset + s[..., None] * dir_a - t[..., None] * dir_b
    # the +tiny keeps the gradient finite where the segments cross
    return torch.sqrt((gap * gap).sum(-1) + 1e-18)


def _quantile(values: torch.Tensor, q: float) -> torch.Tensor:
    return torch.quantile(values.to(torch.float64), q)


def _capsule_radius(segment: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """RADIUS_SHRINK times the RADIUS_QUANTILE quantile of the distances of `points` (M, 3) to `segment` (2, 3)."""
    return RADIUS_SHRINK * _quantile(segment_distances(segment[0], segment[1], points, points), RADIUS_QUANTILE)


def _fit_along_axis(points: torch.Tensor, axis: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Capsule segment (2, 3) and radius () along unit `axis` through the centroid of `points` (M, 3).

    The radius is measured from the axis' stretch that lies a typical cross-section radius inside the points'
    extent; the capsule, rounded ends included, spans RADIUS_SHRINK times that extent.
    """
    along = points @ axis
    low, high = (_quantile(along, q) for q in EXTENT_QUANTILES)
    half_extent = 0.5 * (high - low)
    centroid = points.mean(0)
    centre = centroid + (0.5 * (low + high) - centroid @ axis) * axis
    relative = points - centre
    offsets = relative @ axis
    cross_radius = _quantile((relative - offsets[:, None] * axis).norm(dim=1), RADIUS_QUANTILE)
    core = (half_extent - cross_radius).clamp_min(0.0)
    radius = _capsule_radius(torch.stack([centre - core * axis, centre + core * axis]), points)
    half_length = (RADIUS_SHRINK * half_extent - radius).clamp_min(0.0)
    return torch.stack([centre - half_length * axis, centre + half_length * axis]), radius


def _principal_axis(points: torch.Tensor) -> torch.Tensor:
    relative = points - points.mean(0)
    return torch.linalg.eigh(relative.T @ relative).eigenvectors[:, -1]


@dataclass
class BodyCapsules:
    """Capsules of the body parts in `names`, each moved rigidly by one joint's transform.

    names:       C part names (see `PARTS`)
    carriers:    (C,) int64 joint whose transform moves each capsule
    endpoints:   (C, 2, 3) float64 canonical segment ends, metres
    radii:       (C,) float64 metres
    rest_joints: (24, 3) float64 canonical joint positions, metres
    pairs:       (P, 2) int64 indices of capsules that may not touch
    """

    names: tuple[str, ...]
    carriers: torch.Tensor
    endpoints: torch.Tensor
    radii: torch.Tensor
    rest_joints: torch.Tensor
    pairs: torch.Tensor

    @classmethod
    def from_points(cls, points: torch.Tensor, weights: torch.Tensor, rest_joints: torch.Tensor) -> BodyCapsules:
        """Capsules fitted to canonical surface points.

        points:      (N, 3) canonical positions, metres (an avatar's Gaussian means or a template's vertices)
        weights:     (N, 24) their skinning weights
        rest_joints: (24, 3) canonical joint positions, metres
        """
        points = points.detach().to(torch.float64)
        rest_joints = rest_joints.detach().to(torch.float64)
        dominant = weights.detach().argmax(dim=1)
        lateral = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
        kept: list[_Part] = []
        endpoints, radii = [], []
        for part in PARTS:
            mask = torch.zeros_like(dominant, dtype=torch.bool)
            for joint in part.joints:
                mask |= dominant == joint
            if int(mask.sum()) < MIN_PART_POINTS:
                continue
            part_points = points[mask]
            if part.shape == "bone":
                bone = torch.stack([rest_joints[part.joints[0]], rest_joints[part.child]])
                radius = _capsule_radius(bone, part_points)
                # the capsule's rounded end, not its segment, reaches the joint
                start = bone[0] + (bone[1] - bone[0]) * torch.clamp(radius / (bone[1] - bone[0]).norm(), max=0.5)
                segment = torch.stack([start, bone[1]])
            else:
                axis = lateral if part.shape == "lateral" else _principal_axis(part_points)
                segment, radius = _fit_along_axis(part_points, axis)
            kept.append(part)
            endpoints.append(segment)
            radii.append(radius)
        if not kept:
            raise AvatarPerfectError("no body part has enough points to build the collision capsules")
        pairs = [
            (i, j)
            for i, a in enumerate(kept)
            for j, b in enumerate(kept)
            if i < j
            and frozenset((a.group, b.group)) in FORBIDDEN_CONTACTS
            and _tree_distance(a.joints[0], b.joints[0]) > ATTACHMENT_TREE_DISTANCE
        ]
        return cls(
            names=tuple(part.name for part in kept),
            carriers=torch.tensor([part.carrier for part in kept], dtype=torch.int64),
            endpoints=torch.stack(endpoints),
            radii=torch.stack(radii),
            rest_joints=rest_joints,
            pairs=torch.tensor(pairs, dtype=torch.int64).reshape(-1, 2),
        )

    def posed_endpoints(self, body_pose: torch.Tensor) -> torch.Tensor:
        """body_pose: (B, 24, 3) axis-angle -> (B, C, 2, 3) capsule segment ends at the origin-rooted pose, metres."""
        dtype, device = body_pose.dtype, body_pose.device
        transl = torch.zeros(body_pose.shape[0], 3, dtype=dtype, device=device)
        transforms = forward_kinematics(body_pose, self.rest_joints.to(dtype=dtype, device=device), transl)
        carried = transforms[:, self.carriers.to(device)]  # (B, C, 4, 4)
        ends = self.endpoints.to(dtype=dtype, device=device)
        return (carried[:, :, None, :3, :3] @ ends[None, :, :, :, None])[..., 0] + carried[:, :, None, :3, 3]

    def pair_depths(self, body_pose: torch.Tensor) -> torch.Tensor:
        """body_pose: (B, 24, 3) -> (B, P) penetration depth of each pair in `pairs`, metres (negative: a gap)."""
        if body_pose.shape[-2:] != (NUM_JOINTS, 3):
            raise ValueError(f"body_pose must be (B, {NUM_JOINTS}, 3), got {tuple(body_pose.shape)}")
        ends = self.posed_endpoints(body_pose)
        first, second = ends[:, self.pairs[:, 0]], ends[:, self.pairs[:, 1]]  # (B, P, 2, 3)
        distances = segment_distances(first[..., 0, :], first[..., 1, :], second[..., 0, :], second[..., 1, :])
        radii = self.radii.to(dtype=body_pose.dtype, device=body_pose.device)
        return radii[self.pairs[:, 0]] + radii[self.pairs[:, 1]] - distances

    def penetration(self, body_pose: torch.Tensor) -> torch.Tensor:
        """body_pose: (B, 24, 3) axis-angle -> (B,) sum over the pairs that may not touch of their squared
        penetration depths, metres^2; differentiable, 0 for a pose without intersections."""
        return self.pair_depths(body_pose).clamp_min(0.0).square().sum(-1)

    def intersecting_pairs(self, body_pose: torch.Tensor, tolerance: float = 0.01) -> list[tuple[str, str, float]]:
        """body_pose: (24, 3) -> (part, part, depth in metres) of the pairs that may not touch and penetrate
        deeper than `tolerance` metres, deepest first."""
        with torch.no_grad():
            depths = self.pair_depths(body_pose[None])[0]
        found = [
            (self.names[int(i)], self.names[int(j)], float(depth))
            for (i, j), depth in zip(self.pairs.tolist(), depths.tolist())
            if depth > tolerance
        ]
        return sorted(found, key=lambda item: -item[2])
