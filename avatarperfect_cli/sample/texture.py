"""A procedural clothing texture for the synthetic subject, painted in the template's UV space.

Every face gets a region (skin, hair, shirt, trousers, shoes, or one of the three regions a turntable
video barely shows: inner arms, armpits, crotch) from its canonical position, normal and skinning
weights. Each texel is coloured from the canonical 3D point it maps to, so stripes and checks run
continuously across UV seams; the hidden regions follow whole faces (so per-face labels measure them
exactly), the clothing boundaries are decided per texel (so hems and necklines are smooth).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from avatarperfect_cli.body.base import BodyTemplate
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.render.mesh_raster import rasterize_triangles, vertex_normals

REGIONS: tuple[str, ...] = ("skin", "hair", "shirt", "trousers", "shoes", "inner_arm", "armpit", "crotch")
REGION = {name: index for index, name in enumerate(REGIONS)}
HIDDEN_REGIONS: tuple[str, ...] = ("inner_arm", "armpit", "crotch")

Colour = tuple[float, float, float]

# SMPL joint groups (indices into the 24 joints).
_LEFT_ARM = (16, 18, 20, 22)
_RIGHT_ARM = (17, 19, 21, 23)
_LEGS = (1, 2, 4, 5, 7, 8, 10, 11)
_HEAD = (15,)
_FEET = (7, 8, 10, 11)
_HIDDEN_COLOURS = {"inner_arm": (0.95, 0.05, 0.85), "armpit": (0.0, 0.9, 0.95), "crotch": (0.75, 1.0, 0.0)}
_INNER_ARM_COSINE = 0.85  # inner-arm faces face within ~32 degrees of straight down in the T-pose


@dataclass(frozen=True)
class Preset:
    """A subject: anny phenotype (each value in [0, 1]) and colours (sRGB in [0, 1]). The hidden regions'
    colours are saturated ones no clothing uses."""

    phenotype: dict[str, float]
    skin: Colour
    hair: Colour
    shirt: Colour
    shirt_accent: Colour
    shirt_pattern: str  # "stripes" or "checks"
    trousers: Colour
    shoes: Colour
    hidden: dict[str, Colour] = field(default_factory=lambda: dict(_HIDDEN_COLOURS))


_ADULT = {"age": 0.7, "muscle": 0.5, "weight": 0.5, "height": 0.5, "proportions": 0.5}
PRESETS: dict[str, Preset] = {
    "default": Preset(
        phenotype={**_ADULT, "gender": 0.0},
        skin=(0.86, 0.66, 0.53), hair=(0.17, 0.11, 0.07),
        shirt=(0.13, 0.25, 0.55), shirt_accent=(0.93, 0.92, 0.88), shirt_pattern="stripes",
        trousers=(0.30, 0.31, 0.34), shoes=(0.12, 0.10, 0.09),
    ),
    "female": Preset(
        phenotype={**_ADULT, "gender": 1.0, "muscle": 0.4, "height": 0.4, "age": 0.65},
        skin=(0.62, 0.43, 0.31), hair=(0.06, 0.05, 0.05),
        shirt=(0.78, 0.14, 0.16), shirt_accent=(0.10, 0.09, 0.12), shirt_pattern="checks",
        trousers=(0.17, 0.27, 0.47), shoes=(0.90, 0.89, 0.86),
    ),
    "tall": Preset(
        phenotype={**_ADULT, "gender": 0.2, "height": 0.95, "weight": 0.3, "muscle": 0.7, "proportions": 0.3},
        skin=(0.93, 0.77, 0.66), hair=(0.55, 0.38, 0.18),
        shirt=(0.16, 0.45, 0.24), shirt_accent=(0.95, 0.80, 0.20), shirt_pattern="stripes",
        trousers=(0.08, 0.08, 0.09), shoes=(0.45, 0.26, 0.12),
    ),
    "heavy": Preset(
        phenotype={**_ADULT, "gender": 0.4, "weight": 0.9, "muscle": 0.3, "age": 0.85},
        skin=(0.76, 0.56, 0.42), hair=(0.62, 0.62, 0.60),
        shirt=(0.85, 0.45, 0.10), shirt_accent=(0.35, 0.20, 0.10), shirt_pattern="checks",
        trousers=(0.42, 0.37, 0.28), shoes=(0.20, 0.20, 0.22),
    ),
}  # fmt: skip


def get_preset(name: str) -> Preset:
    """The preset called `name`; AvatarPerfectError naming the known ones otherwise."""
    if name not in PRESETS:
        raise AvatarPerfectError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    return PRESETS[name]


@dataclass
class SubjectTexture:
    """image: (S, S, 3) uint8 texture (row 0 is v = 1); face_regions: (F,) int32 indices into REGIONS."""

    image: np.ndarray
    face_regions: np.ndarray


def face_regions(template: BodyTemplate) -> np.ndarray:
    """(F,) int32 region of each face of `template` (canonical T-pose, SMPL frame), indices into REGIONS."""
    vertices, faces, normals, groups = _surface(template)
    face_normals = normals[faces].mean(axis=1)
    face_normals /= np.maximum(np.linalg.norm(face_normals, axis=1, keepdims=True), 1e-12)
    return _classify(vertices[faces].mean(axis=1), face_normals, groups[faces].mean(axis=1), template, hidden=True)


def _surface(template: BodyTemplate) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """vertices (V, 3), faces (F, 3), unit normals (V, 3) and joint-group weights (V, 5): left arm,
    right arm, legs, head, feet."""
    vertices = template.vertices.double().numpy()
    faces = template.faces.numpy()
    weights = template.weights.double().numpy()
    groups = np.stack([weights[:, list(g)].sum(axis=1) for g in (_LEFT_ARM, _RIGHT_ARM, _LEGS, _HEAD, _FEET)], axis=1)
    return vertices, faces, vertex_normals(vertices, faces), groups


def _classify(
    points: np.ndarray, normals: np.ndarray, groups: np.ndarray, template: BodyTemplate, hidden: bool
) -> np.ndarray:
    """(N,) int32 regions of surface points (N, 3) with unit normals (N, 3) and joint-group weights
    (N, 5) (see `_surface`). hidden=False leaves out the hidden regions (the clothes underneath)."""
    joints = template.rest_joints.double().numpy()
    x, y = points[:, 0], points[:, 1]
    left_arm, right_arm, leg, head, feet = (groups[:, k] > 0.5 for k in range(5))
    waist_y = joints[0, 1] + 0.35 * (joints[3, 1] - joints[0, 1])
    neck_y = joints[12, 1] - 0.25 * (joints[12, 1] - joints[9, 1])

    regions = np.full(len(points), REGION["shirt"], dtype=np.int32)
    regions[(y < waist_y) | leg] = REGION["trousers"]
    regions[(y > neck_y) | head] = REGION["skin"]
    sleeve_reach = 0.4  # short sleeves cover this fraction of the upper arm
    for on_side, shoulder, elbow, wrist, sign in ((left_arm, 16, 18, 20, 1.0), (right_arm, 17, 19, 21, -1.0)):
        out = sign * (x - joints[shoulder, 0])  # distance out from the shoulder joint
        regions[on_side & (out > sleeve_reach * sign * (joints[elbow, 0] - joints[shoulder, 0]))] = REGION["skin"]
        if not hidden:
            continue
        # Inner arm: the underside in the T-pose, which faces the torso once the arms hang down.
        axis = joints[wrist] - joints[shoulder]
        axis /= np.linalg.norm(axis)
        radial = points - joints[shoulder]
        radial -= np.outer(radial @ axis, axis)
        radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-12)
        down = np.array([0.0, -1.0, 0.0]) + axis * axis[1]
        down /= np.linalg.norm(down)
        on_arm = on_side & (out > 0.05) & (out < sign * (joints[wrist, 0] - joints[shoulder, 0]) - 0.02)
        regions[on_arm & (radial @ down > _INNER_ARM_COSINE)] = REGION["inner_arm"]
        # Armpit: the hollow under the shoulder joint, where arm and torso meet.
        pit = joints[shoulder] + np.array([-sign * 0.02, -0.07, 0.0])
        near_pit = (np.linalg.norm(points - pit, axis=1) < 0.07) & (y < joints[shoulder, 1] - 0.02)
        regions[near_pit & (normals[:, 1] < 0.3) & (np.abs(normals[:, 2]) < 0.6)] = REGION["armpit"]
    if hidden:
        # Crotch: the inward-facing tops of the thighs and the downward-facing surface between them.
        hip_y = 0.5 * (joints[1, 1] + joints[2, 1])
        knee_y = 0.5 * (joints[4, 1] + joints[5, 1])
        upper_thigh = (y > knee_y + 0.7 * (hip_y - knee_y)) & (y < hip_y + 0.02)
        inward = -np.sign(x) * normals[:, 0] > 0.7
        between = (np.abs(x) < 0.06) & (normals[:, 1] < -0.5) & (y < hip_y + 0.02)
        regions[(upper_thigh & inward & leg) | between] = REGION["crotch"]

    head_vertices = template.vertices.double().numpy()[template.weights[:, list(_HEAD)].sum(1).numpy() > 0.5]
    regions[head & _hair_mask(points, head_vertices)] = REGION["hair"]
    ankle_y = 0.5 * (joints[7, 1] + joints[8, 1])
    regions[feet & (y < ankle_y + 0.03)] = REGION["shoes"]
    return regions


def _hair_mask(points: np.ndarray, head_vertices: np.ndarray) -> np.ndarray:
    """(N,) bool: points on the scalp, judged by their direction from the head's bounding-box centre."""
    low, high = head_vertices.min(axis=0), head_vertices.max(axis=0)
    direction = (points - 0.5 * (low + high)) / (0.5 * (high - low))
    return (direction[:, 1] > 0.35) | ((direction[:, 2] < -0.1) & (direction[:, 1] > -0.35))


def paint_texture(template: BodyTemplate, preset: Preset, size: int = 1024, seed: int = 0) -> SubjectTexture:
    """Paint the (size, size) UV texture of `template` dressed as `preset`. Deterministic for a seed.

    Texels outside every UV triangle take their painted neighbours' colour (a few texels deep), so
    bilinear lookups near seams never mix in unpainted ones.
    """
    if template.uvs is None or template.face_uvs is None:
        raise ValueError("the body template has no texture coordinates")
    regions = face_regions(template)
    vertices, faces, normals, groups = _surface(template)
    uvs = template.uvs.double().numpy()
    screen = np.stack([uvs[:, 0] * size, (1.0 - uvs[:, 1]) * size, np.ones(len(uvs))], axis=1)
    face_id, bary = rasterize_triangles(screen, template.face_uvs.numpy(), size, size)
    painted = face_id >= 0
    ids = face_id[painted]
    weights = bary[painted]
    corners = faces[ids]
    points = np.einsum("nk,nkc->nc", weights, vertices[corners])
    texel_normals = np.einsum("nk,nkc->nc", weights, normals[corners])
    texel_normals /= np.maximum(np.linalg.norm(texel_normals, axis=1, keepdims=True), 1e-12)
    texel_groups = np.einsum("nk,nkc->nc", weights, groups[corners])
    texel_regions = _classify(points, texel_normals, texel_groups, template, hidden=False)
    is_hidden = np.isin(regions[ids], [REGION[name] for name in HIDDEN_REGIONS])
    texel_regions[is_hidden] = regions[ids][is_hidden]

    rng = np.random.default_rng(seed)
    colours = _region_colours(texel_regions, points, preset, template.rest_joints.double().numpy(), rng)
    image = np.zeros((size, size, 3), dtype=np.float32)
    image[painted] = colours
    image = _pad_islands(image, painted, passes=4)
    return SubjectTexture(np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8), regions)


class _Noise:
    """A smooth pseudo-random field in about [-1, 1] over 3D points: a sum of random plane waves with
    wavelengths around `scale` metres, stretched by `stretch` along each axis."""

    def __init__(self, rng: np.random.Generator, scale: float, terms: int, stretch: tuple[float, ...] = (1, 1, 1)):
        directions = rng.normal(size=(terms, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        frequencies = 2.0 * np.pi / (scale * rng.uniform(0.6, 1.4, size=terms))
        self.waves = (directions * frequencies[:, None] * np.asarray(stretch)).T.astype(np.float32)  # (3, terms)
        self.phases = rng.uniform(0.0, 2.0 * np.pi, size=terms).astype(np.float32)
        self.norm = np.sqrt(terms / 2.0)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(N,) float64 field values at points (N, 3)."""
        return np.sin(points.astype(np.float32) @ self.waves + self.phases).sum(axis=1, dtype=np.float64) / self.norm


def _region_colours(
    regions: np.ndarray, points: np.ndarray, preset: Preset, joints: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """(N, 3) colours of texels with the given regions at canonical points (N, 3)."""
    mottle = _Noise(rng, 0.08, terms=6)  # soft, low-contrast variation
    grain = _Noise(rng, 0.006, terms=8)  # fabric grain
    streaks = _Noise(rng, 0.02, terms=8, stretch=(4.0, 0.3, 4.0))  # hair strands, mostly vertical
    colours = np.empty((len(points), 3))

    def tone(base: Colour, amount: np.ndarray) -> np.ndarray:
        return np.asarray(base)[None] * (1.0 + amount)[:, None]

    def at(region: str) -> tuple[np.ndarray, np.ndarray]:
        mask = regions == REGION[region]
        return mask, points[mask]

    mask, p = at("skin")
    colours[mask] = tone(preset.skin, 0.04 * mottle(p))
    mask, p = at("hair")
    colours[mask] = tone(preset.hair, 0.25 * streaks(p))

    # Shirt: stripes along the body axis (torso) or along the arm (sleeves); checks add a second set
    # of bands around the body, so a misplaced or mirrored patch is easy to spot.
    mask, p = at("shirt")
    x, y, z = p.T
    shoulder_x = abs(joints[16, 0])
    on_sleeve = np.abs(x) > shoulder_x
    stripe = (np.floor(np.where(on_sleeve, np.abs(x) - shoulder_x, y) / 0.05) % 2 == 0).astype(np.float64)
    if preset.shirt_pattern == "checks":
        turns = np.where(on_sleeve, np.arctan2(z, y - joints[16, 1]) * 8.0, np.arctan2(x, z) * 16.0) / (2.0 * np.pi)
        stripe = 0.5 * (stripe + (np.floor(turns) % 2 == 0))
    shirt = stripe[:, None] * np.asarray(preset.shirt_accent) + (1.0 - stripe[:, None]) * np.asarray(preset.shirt)
    # A round badge on the chest tells front from back.
    badge = (np.hypot(x - 0.09, y - joints[9, 1] - 0.06) < 0.035) & (z > joints[9, 2])
    shirt[badge] = np.asarray(preset.hair) * 0.5 + np.array([0.5, 0.45, 0.1])
    colours[mask] = shirt * (1.0 + 0.03 * grain(p))[:, None]

    mask, p = at("trousers")
    trousers = tone(preset.trousers, 0.05 * grain(p) + 0.03 * mottle(p))
    waist_y = joints[0, 1] + 0.35 * (joints[3, 1] - joints[0, 1])
    trousers[np.abs(p[:, 1] - waist_y + 0.02) < 0.018] = np.asarray(preset.shoes) * 0.7  # belt
    colours[mask] = trousers
    mask, p = at("shoes")
    shoes = tone(preset.shoes, 0.03 * grain(p))
    shoes[p[:, 1] < p[:, 1].min(initial=np.inf) + 0.02] = np.array([0.88, 0.86, 0.82])  # soles
    colours[mask] = shoes

    # The hidden regions: saturated colours in a fine 3D checker, so any leak or blur shows.
    light = {"inner_arm": (1.0, 0.85, 1.0), "armpit": (0.0, 0.35, 0.45), "crotch": (0.1, 0.25, 0.0)}
    for name in HIDDEN_REGIONS:
        mask, p = at(name)
        checker = (np.floor(p / 0.02).sum(axis=1) % 2 == 0)[:, None]
        colours[mask] = np.where(checker, np.asarray(preset.hidden[name]), np.asarray(light[name]))
    return colours


def _pad_islands(image: np.ndarray, painted: np.ndarray, passes: int) -> np.ndarray:
    """Grow the painted UV islands by `passes` texels: each unpainted texel among the 8 neighbours of
    painted ones takes their mean colour."""
    image = image.astype(np.float32)
    painted = painted.copy()
    for _ in range(passes):
        weight = painted.astype(np.float32)
        total = cv2.boxFilter(image * weight[..., None], -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        count = cv2.boxFilter(weight, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        grow = ~painted & (count > 0)
        image[grow] = total[grow] / count[grow, None]
        painted |= grow
    return image
