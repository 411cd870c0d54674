"""Body models (templates in SMPL's frame and T-pose) and the SMPL 24-joint skeleton that poses them."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from avatarperfect_cli.body.base import NUM_JOINTS, SMPL_JOINT_NAMES, SMPL_PARENTS, BodyTemplate
from avatarperfect_cli.body.skeleton import (
    blend_transforms, forward_kinematics, matrix_to_quaternion, posed_joints, skin_gaussians, skin_points,
)  # fmt: skip
from avatarperfect_cli.errors import AvatarPerfectError
from avatarperfect_cli.rotations import axis_angle_to_matrix, quaternion_to_matrix

BODY_MODELS = ("anny", "smpl")


def load_body_template(
    name: str = "anny",
    *,
    smpl_model_dir: Path | None = None,
    phenotype: dict[str, float] | None = None,
    cache_dir: Path | None = None,
    gender: str = "neutral",
    betas: list[float] | None = None,
) -> BodyTemplate:
    """The canonical template of body model `name`.

    anny: shaped by `phenotype` (see `anny_model.PHENOTYPES`), cached under `cache_dir`.
    smpl: read from the user's `smpl_model_dir`, with `gender` and shape `betas`.
    """
    if name == "anny":
        from avatarperfect_cli.body.anny_model import load_anny_template

        return load_anny_template(phenotype, cache_dir)
    if name == "smpl":
        if smpl_model_dir is None:
            raise AvatarPerfectError("the smpl body model needs the folder of your SMPL model files (--smpl-model-dir)")
        from avatarperfect_cli.body.smpl_model import load_smpl_template

        return load_smpl_template(smpl_model_dir, gender, betas)
    raise AvatarPerfectError(f"unknown body model {name!r}; choose one of {', '.join(BODY_MODELS)}")


def load_described_template(description: Mapping[str, Any], smpl_model_dir: Path | None = None) -> BodyTemplate:
    """The template an avatar's `body_model` metadata describes ({"name": "anny", "phenotype": {...}} or
    {"name": "smpl", "betas": [...]}, as train-initial writes it, with "bone_offsets" (24 x 3 metres) where
    it corrected the skeleton); SMPL also needs `smpl_model_dir`."""
    if "name" not in description:
        raise AvatarPerfectError("the avatar does not name its body model (an avatar from before it was recorded)")
    template = load_body_template(
        str(description["name"]), smpl_model_dir=smpl_model_dir, phenotype=description.get("phenotype"), betas=description.get("betas")
    )
    if description.get("bone_offsets") is None:
        return template
    try:
        bone_offsets = torch.tensor(description["bone_offsets"], dtype=torch.float32)
    except (TypeError, ValueError):
        bone_offsets = torch.empty(0)
    if bone_offsets.shape != (NUM_JOINTS, 3) or not bone_offsets.isfinite().all():
        raise AvatarPerfectError("the avatar's body_model 'bone_offsets' is not a 24 x 3 list of finite numbers")
    return template.with_bone_offsets(bone_offsets)


__all__ = [
    "BODY_MODELS",
    "NUM_JOINTS",
    "SMPL_JOINT_NAMES",
    "SMPL_PARENTS",
    "BodyTemplate",
    "axis_angle_to_matrix",
    "blend_transforms",
    "forward_kinematics",
    "load_body_template",
    "load_described_template",
    "matrix_to_quaternion",
    "posed_joints",
    "quaternion_to_matrix",
    "skin_gaussians",
    "skin_points",
]
