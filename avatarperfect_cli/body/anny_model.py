"""The default body: the `anny` parametric model (Apache-2.0, MakeHuman CC0 data), as an SMPL-like template.

Anny's 104-bone rig is mapped onto SMPL's 24 joints (`ANNY_BONES`), its frame (Z up, -Y front) is turned
into SMPL's (+Y up, +Z front), and its A-pose rest is posed into a T-pose, SMPL's zero pose. The finished
template is cached per phenotype as an .npz, so later loads need neither anny nor warp.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from rich.console import Console

from avatarperfect_cli.body.base import NUM_JOINTS, BodyTemplate
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.io.atomic import atomic_path

if TYPE_CHECKING:
    import anny

PHENOTYPES: tuple[str, ...] = ("gender", "age", "muscle", "weight", "height", "proportions")
DEFAULT_PHENOTYPE_VALUE = 0.5
# Bump when the template construction changes, so stale cached templates are rebuilt.
TEMPLATE_VERSION = 1

# Anny bones driven by each SMPL joint; other bones follow their nearest mapped ancestor.
ANNY_BONES: tuple[tuple[str, ...], ...] = (
    ("root",),
    ("upperleg01.L",),
    ("upperleg01.R",),
    ("spine04",),
    ("lowerleg01.L",),
    ("lowerleg01.R",),
    ("spine02",),
    ("foot.L",),
    ("foot.R",),
    ("spine01",),
    tuple(f"toe{i}-1.L" for i in range(1, 6)),
    tuple(f"toe{i}-1.R" for i in range(1, 6)),
    ("neck01",),
    ("clavicle.L",),
    ("clavicle.R",),
    ("head",),
    ("upperarm01.L",),
    ("upperarm01.R",),
    ("lowerarm01.L",),
    ("lowerarm01.R",),
    ("wrist.L",),
    ("wrist.R",),
    tuple(f"metacarpal{i}.L" for i in range(1, 5)) + ("finger1-1.L",),
    tuple(f"metacarpal{i}.R" for i in range(1, 5)) + ("finger1-1.R",),
)
# Arm chains straightened along +-X for the T-pose: the shoulder, elbow and wrist joints, the bone head
# each segment points at (the next joint; the hand aims at its middle knuckle), the hand joint that turns
# with the wrist, and the side (+1 left).
_ARM_CHAINS: tuple[tuple[tuple[int, int, int], tuple[str, str, str], int, float], ...] = (
    ((16, 18, 20), ("lowerarm01.L", "wrist.L", "finger3-1.L"), 22, 1.0),
    ((17, 19, 21), ("lowerarm01.R", "wrist.R", "finger3-1.R"), 23, -1.0),
)
# SMPL frame from anny's: (x, y, z) -> (x, z, -y), a -90 degree turn about X.
ANNY_TO_SMPL = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], dtype=torch.float64)


def default_cache_dir() -> Path:
    """The anny cache folder: $AVATARPERFECT_CACHE/anny, else ~/.cache/avatarperfect/anny."""
    root = os.environ.get("AVATARPERFECT_CACHE")
    return (Path(root) if root else Path.home() / ".cache" / "avatarperfect") / "anny"


def full_phenotype(phenotype: dict[str, float] | None) -> dict[str, float]:
    """Every phenotype in `PHENOTYPES`, missing ones at 0.5; raises AvatarPerfectError for unknown names or
    values outside [0, 1]."""
    given = dict(phenotype or {})
    unknown = sorted(set(given) - set(PHENOTYPES))
    if unknown:
        raise AvatarPerfectError(f"unknown anny phenotype {', '.join(unknown)}; known: {', '.join(PHENOTYPES)}")
    values = {name: float(given.get(name, DEFAULT_PHENOTYPE_VALUE)) for name in PHENOTYPES}
    for name, value in values.items():
        if not 0.0 <= value <= 1.0:
            raise AvatarPerfectError(f"anny phenotype {name}={value} is outside [0, 1]")
    return values


def load_anny_template(
    phenotype: dict[str, float] | None = None, cache_dir: Path | None = None, progress: bool = True
) -> BodyTemplate:
    """The anny body for `phenotype` (names in `PHENOTYPES`, values in [0, 1], default 0.5) as a T-pose
    template in SMPL's frame, float32, metres.

    cache_dir: the folder holding anny's model cache and our templates
               (default `default_cache_dir()`). The first anny build there takes about 2 minutes and 0.8 GB.
    progress:  print a note to stderr before that first build.
    """
    values = full_phenotype(phenotype)
    cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    key = json.dumps(
        {"template": TEMPLATE_VERSION, "anny": importlib.metadata.version("anny"), "phenotype": values},
        sort_keys=True,
    )
    path = cache_dir / "templates" / f"anny-{hashlib.sha256(key.encode()).hexdigest()[:16]}.npz"
    if path.exists():
        return BodyTemplate.load(path)
    template = build_anny_template(load_anny_model(cache_dir, progress), values)
    with atomic_path(path) as temporary:
        template.save(temporary)
    return template


def load_anny_model(cache_dir: Path, progress: bool = True) -> anny.Anny:
    """anny's full-body model (float64) with its cache under `cache_dir`.

    Dense torch skinning ("lbs") keeps warp out: neither the build nor posing then imports it.
    """
    cache_dir.mkdir(parents=True, exist_ok=True)
    if progress and not any(cache_dir.glob("v*/build_compact_model_data_*.safetensors")):
        Console(stderr=True).print("building the anny body model cache (first run, about 2 minutes)...")
    import anny
    import anny.paths

    anny.paths.set_anny_cache_path(cache_dir)
    return anny.Anny(skinning_method="lbs")


def bone_joints(bone_labels: list[str], bone_parents: list[int]) -> torch.Tensor:
    """(bones,) int64: the SMPL joint that drives each anny bone (its own, or its nearest mapped ancestor's)."""
    mapped = {bone: joint for joint, bones in enumerate(ANNY_BONES) for bone in bones}
    missing = sorted(set(mapped) - set(bone_labels))
    if missing:
        raise RuntimeError(f"anny rig lacks the bones {missing}")
    joints = []
    for bone in range(len(bone_labels)):
        while bone_labels[bone] not in mapped:  # the root is mapped, so this ends
            bone = bone_parents[bone]
        joints.append(mapped[bone_labels[bone]])
    return torch.tensor(joints)


def _aligning_rotation(source: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(3, 3) smallest rotation turning the direction of `source` onto that of `target` (not opposite)."""
    a = source / source.norm()
    b = target / target.norm()
    axis = torch.linalg.cross(a, b)
    cosine = torch.dot(a, b)
    k = torch.zeros(3, 3, dtype=a.dtype)
    k[0, 1], k[0, 2], k[1, 2] = -axis[2], axis[1], -axis[0]
    k = k - k.T
    return torch.eye(3, dtype=a.dtype) + k + k @ k / (1.0 + cosine)


def t_pose_rotations(rest_bone_heads: torch.Tensor, bone_labels: list[str]) -> torch.Tensor:
    """(24, 3, 3) world rotations (anny frame) that turn anny's A-pose into a T-pose.

    Along each arm, the upper arm, forearm and hand are turned in turn (each by the smallest rotation,
    carrying the rest of the arm along) to point straight out along +-X. Other joints keep their rest.
    rest_bone_heads: (bones, 3) anny rest (A-pose) bone heads, metres.
    """
    index = {label: i for i, label in enumerate(bone_labels)}
    rotations = torch.eye(3, dtype=rest_bone_heads.dtype).repeat(NUM_JOINTS, 1, 1)
    for joints, ends, hand, side in _ARM_CHAINS:
        target = torch.tensor([side, 0.0, 0.0], dtype=rest_bone_heads.dtype)
        turned = torch.eye(3, dtype=rest_bone_heads.dtype)
        for joint, end in zip(joints, ends):
            segment = rest_bone_heads[index[end]] - rest_bone_heads[index[ANNY_BONES[joint][0]]]
            turned = _aligning_rotation(turned @ segment, target) @ turned
            rotations[joint] = turned
        rotations[hand] = turned
    return rotations


def anny_pose_parameters(
    rest: dict[str, torch.Tensor], joints_of_bones: torch.Tensor, joint_rotations: torch.Tensor, root: torch.Tensor
) -> torch.Tensor:
    """anny "world-orient" pose parameters that give every bone the world rotation of its SMPL joint.

    rest:             anny's rest model output ("rest_bone_poses": (1, bones, 4, 4))
    joints_of_bones:  (bones,) from `bone_joints`
    joint_rotations:  (B, 24, 3, 3) world rotations in anny's frame, from the A-pose rest
    root:             (B, 3) posed position of the root bone's head, anny frame, metres
    returns           (B, bones, 4, 4)
    """
    rest_orientations = rest["rest_bone_poses"][:, :, :3, :3]
    parameters = torch.zeros(joint_rotations.shape[0], len(joints_of_bones), 4, 4, dtype=joint_rotations.dtype)
    parameters[:, :, :3, :3] = joint_rotations[:, joints_of_bones] @ rest_orientations
    parameters[:, 0, :3, 3] = root
    parameters[:, :, 3, 3] = 1.0
    return parameters


def joint_weights(model: anny.Anny) -> torch.Tensor:
    """(V, 24) float64 skinning weights of `model`'s vertices over the SMPL joints (rows sum to 1); anny's
    skinning does not depend on the phenotype."""
    joints_of_bones = bone_joints(model.bone_labels, model.bone_parents)
    bone_weights = torch.zeros(model.template_vertices.shape[0], len(model.bone_labels), dtype=torch.float64)
    bone_weights.scatter_add_(1, model.vertex_bone_indices, model.vertex_bone_weights)
    weights = torch.zeros(bone_weights.shape[0], NUM_JOINTS, dtype=torch.float64).index_add_(
        1, joints_of_bones, bone_weights
    )
    return weights / weights.sum(1, keepdim=True)


def anny_shape(model: anny.Anny, phenotype: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The T-pose of `model` for phenotype values (6,) float64 in `PHENOTYPES` order, or a batch of them
    (B, 6), differentiable in them (one body: about 30 ms forward and 12 ms backward on 2 CPU cores; a batch
    of 7 costs about as much as one).

    returns vertices (V, 3) and rest joints (24, 3), or (B, V, 3) and (B, 24, 3); float64, SMPL frame, metres
    """
    batch = phenotype.reshape(-1, len(PHENOTYPES))
    values = {name: batch[:, index] for index, name in enumerate(PHENOTYPES)}
    rest = model(phenotype_kwargs=values)
    heads = rest["rest_bone_heads"]
    joints_of_bones = bone_joints(model.bone_labels, model.bone_parents)
    corrections = torch.stack([t_pose_rotations(body_heads, model.bone_labels) for body_heads in heads])
    t_pose = model(
        anny_pose_parameters(rest, joints_of_bones, corrections, heads[:, 0]),
        phenotype_kwargs=values,
        pose_parameterization="world-orient",
    )
    posed_heads = t_pose["bone_poses"][:, :, :3, 3]
    rest_joints = torch.stack(
        [posed_heads[:, [model.bone_labels.index(bone) for bone in bones]].mean(1) for bones in ANNY_BONES], dim=1
    )
    vertices, rest_joints = t_pose["vertices"] @ ANNY_TO_SMPL.T, rest_joints @ ANNY_TO_SMPL.T
    if phenotype.dim() == 1:
        return vertices[0], rest_joints[0]
    return vertices, rest_joints


def build_anny_template(model: anny.Anny, phenotype: dict[str, float]) -> BodyTemplate:
    """The T-pose template of `model` for `phenotype` (all of `PHENOTYPES`), float32, SMPL frame."""
    values = torch.tensor([phenotype[name] for name in PHENOTYPES], dtype=torch.float64)
    with torch.no_grad():
        vertices, rest_joints = anny_shape(model, values)
    return BodyTemplate(
        vertices=vertices.float(),
        faces=model.faces.long(),
        weights=joint_weights(model).float(),
        rest_joints=rest_joints.float(),
        uvs=model.texture_coordinates.float(),
        face_uvs=model.face_texture_coordinate_indices.long(),
    )
