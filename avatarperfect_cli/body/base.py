"""The one interface every body model provides: a template at setup time."""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path
from typing import BinaryIO

import numpy as np
import torch

# SMPL's 24-joint kinematic tree: parent of each joint, -1 for the root (pelvis).
SMPL_PARENTS: tuple[int, ...] = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21)
SMPL_JOINT_NAMES: tuple[str, ...] = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
    "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
    "left_hand", "right_hand",
)  # fmt: skip
NUM_JOINTS = 24
# Left/right joint pairs of the SMPL tree (+X is the body's left).
SMPL_MIRROR: tuple[int, ...] = (0, 2, 1, 3, 5, 4, 6, 8, 7, 9, 11, 10, 12, 14, 13, 15, 17, 16, 19, 18, 21, 20, 23, 22)


def joint_displacements(bone_offsets: torch.Tensor) -> torch.Tensor:
    """(..., 24, 3) how far each rest joint moves when every bone's offset from its parent joint changes by
    `bone_offsets` (..., 24, 3) metres (the root's entry moves the whole body): the sum along its chain."""
    displacements = [bone_offsets[..., 0, :]]
    for joint in range(1, NUM_JOINTS):
        displacements.append(displacements[SMPL_PARENTS[joint]] + bone_offsets[..., joint, :])
    return torch.stack(displacements, dim=-2)


@dataclass
class BodyTemplate:
    """A canonical body in SMPL's frame and zero pose (T-pose): +Y up, +Z the body's front, metres.

    vertices:    (V, 3) canonical vertex positions
    faces:       (F, 3) int64 triangle vertex indices, counter-clockwise seen from outside
    weights:     (V, 24) skinning weights over the SMPL joints; rows sum to 1
    rest_joints: (24, 3) joint positions in the canonical pose
    uvs:         (T, 2) texture coordinates in [0, 1], or None
    face_uvs:    (F, 3) int64 indices into `uvs`, or None
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    weights: torch.Tensor
    rest_joints: torch.Tensor
    uvs: torch.Tensor | None = None
    face_uvs: torch.Tensor | None = None

    def with_bone_offsets(self, bone_offsets: torch.Tensor) -> BodyTemplate:
        """The template with its skeleton corrected: each bone's offset from its parent joint changed by
        `bone_offsets` (24, 3) metres, canonical frame; every vertex moves by its skinning blend of the
        joints' displacements, so a longer thigh carries the shin and the foot with the knee and the ankle."""
        displacements = joint_displacements(bone_offsets.to(self.rest_joints.dtype))
        return BodyTemplate(
            self.vertices + self.weights @ displacements.to(self.vertices.dtype),
            self.faces,
            self.weights,
            self.rest_joints + displacements,
            self.uvs,
            self.face_uvs,
        )

    def save(self, file: Path | BinaryIO) -> None:
        """Write the template's arrays to an uncompressed .npz (`load` reads it back to the bit)."""
        arrays = {field.name: getattr(self, field.name) for field in fields(self)}
        np.savez(file, **{name: value.numpy() for name, value in arrays.items() if value is not None})

    @classmethod
    def load(cls, path: Path) -> BodyTemplate:
        """The template `save` wrote to `path`; a file numpy cannot read raises what numpy raises (OSError,
        zipfile.BadZipFile, KeyError, ValueError...)."""
        with np.load(path) as data:
            return cls(**{name: torch.from_numpy(data[name]) for name in data.files})
