"""The ground truth of a synthetic subject in any pose: its anny body in its painted clothes.

`make_sample` renders its videos through `SyntheticSubject.render_vertices`, so `SyntheticSubject.render`
at a frame's stored pose gives that frame's pixels. The `labels` of a render name the texture region of
each pixel (indices into texture.REGIONS), which locates the hidden regions (texture.HIDDEN_REGIONS).
`unseen_faces` finds the surface a video never showed, whatever its texture region (soles, the top of
the head): the exact counterpart of the barely seen Gaussians an avatar's visibility estimates.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from avatarperfect_cli.body import load_body_template
from avatarperfect_cli.body.base import BodyTemplate
from avatarperfect_cli.body.retarget import retarget_pose
from avatarperfect_cli.body.skeleton import forward_kinematics, skin_points
from avatarperfect_cli.body.anny_model import full_phenotype
from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.io.json_file import read_json_object
from avatarperfect_cli.render.camera import Camera
from avatarperfect_cli.render.mesh_raster import MeshRender, render_mesh, vertex_normals
from avatarperfect_cli.sample.texture import PRESETS, SubjectTexture, get_preset, paint_texture

TEXTURE_SIZE = 1024
AMBIENT = 0.55  # share of unshaded light in the headlight shading
_NOT_SYNTHETIC = "not a synthetic subject made by 'avatarperfect make-sample'"


@dataclass
class SyntheticSubject:
    """The anny body of `preset` (texture.PRESETS) dressed in the texture painted with `seed`.

    template: the canonical body; texture: its (TEXTURE_SIZE, TEXTURE_SIZE) UV texture and face regions
    """

    template: BodyTemplate
    texture: SubjectTexture
    preset: str
    seed: int

    @classmethod
    def create(cls, preset: str = "default", seed: int = 0, phenotype: dict[str, float] | None = None) -> SyntheticSubject:
        """The subject make_sample renders for these arguments: the preset's clothes on the preset's body, or
        on the anny body of `phenotype` (AvatarPerfectError for an unknown preset or phenotype)."""
        subject_preset = get_preset(preset)
        template = load_body_template("anny", phenotype=phenotype or subject_preset.phenotype)
        return cls(template, paint_texture(template, subject_preset, TEXTURE_SIZE, seed), preset, seed)

    @classmethod
    def from_dataset(cls, folder: Path) -> SyntheticSubject:
        """The subject of a dataset folder written by make_sample (its subject.json names the preset and seed).

        Raises InputFileError "FOLDER: not a synthetic subject made by 'avatarperfect make-sample' (why)"
        for any other folder.
        """
        folder = Path(folder)
        path = folder / "subject.json"
        if not path.is_file():
            raise InputFileError(folder, f"{_NOT_SYNTHETIC} (no subject.json)")
        subject = read_json_object(path, "subject", 1)
        preset, seed = subject.get("preset"), subject.get("seed")
        if subject.get("body_model") != "anny" or preset not in PRESETS:
            raise InputFileError(folder, f"{_NOT_SYNTHETIC} (subject.json names no anny preset)")
        if not isinstance(seed, int) or isinstance(seed, bool):
            raise InputFileError(folder, f"{_NOT_SYNTHETIC} (subject.json has no integer seed)")
        phenotype = subject.get("phenotype")
        try:
            full_phenotype(phenotype if isinstance(phenotype, dict) else {"": phenotype})
        except AvatarPerfectError as error:
            raise InputFileError(folder, f"{_NOT_SYNTHETIC} ({error})") from None
        return cls.create(preset, seed, phenotype)

    def render(self, body_pose: torch.Tensor, transl: torch.Tensor, camera: Camera) -> MeshRender:
        """The subject at one pose, on white. body_pose: (24, 3) SMPL axis-angle, radians; transl: (3,) metres,
        used as given (make_sample's stored translations are already grounded)."""
        vertices = skin_template(self.template, torch.as_tensor(body_pose)[None], torch.as_tensor(transl)[None])
        return self.render_vertices(vertices[0].numpy(), camera)

    def render_posed_like(self, body_pose: torch.Tensor, transl: torch.Tensor, rest_joints: torch.Tensor, camera: Camera) -> MeshRender:
        """The subject in the pose another skeleton shows, on white: its joints where `rest_joints` (24, 3) posed by
        body_pose (24, 3) and transl (3,) put theirs (`body.retarget`), as a person pictures the subject in the
        pose an avatar on that skeleton shows, where it stands. With the subject's own skeleton this is `render`."""
        body_pose, transl = retarget_pose(body_pose, transl, rest_joints, self.template.rest_joints)
        return self.render(body_pose, transl, camera)

    def render_vertices(self, vertices: np.ndarray, camera: Camera) -> MeshRender:
        """The template posed at `vertices` (V, 3) float64 metres, world frame: shaded, textured, 2x2
        supersampled, on white, with labels = the texture region of each pixel (-1 on the background)."""
        faces = self.template.faces.numpy()
        return render_mesh(
            vertices, faces, self.template.uvs.double().numpy(), self.template.face_uvs.numpy(), self.texture.image,
            camera, normals=vertex_normals(vertices, faces), ambient=AMBIENT, face_labels=self.texture.face_regions,
        )  # fmt: skip

    def face_ids(self, body_pose: torch.Tensor, transl: torch.Tensor, camera: Camera) -> np.ndarray:
        """(H, W) int32 index of the template face each pixel shows (most of its subsamples), -1 on the
        background. body_pose: (24, 3) axis-angle, radians; transl: (3,) metres."""
        vertices = skin_template(self.template, torch.as_tensor(body_pose)[None], torch.as_tensor(transl)[None])[0].numpy()
        faces = self.template.faces.numpy()
        face_index = np.arange(len(faces), dtype=np.int32)
        return render_mesh(
            vertices, faces, self.template.uvs.double().numpy(), self.template.face_uvs.numpy(), self.texture.image,
            camera, face_labels=face_index,
        ).labels  # fmt: skip

    def unseen_faces(self, body_poses: torch.Tensor, transls: torch.Tensor, camera: Camera) -> np.ndarray:
        """(F,) bool: the template faces no pixel of any frame shows. body_poses: (T, 24, 3); transls: (T, 3)."""
        seen = np.zeros(len(self.template.faces), dtype=bool)
        for body_pose, transl in zip(body_poses, transls):
            ids = self.face_ids(body_pose, transl, camera)
            seen[ids[ids >= 0]] = True
        return ~seen


def skin_template(template: BodyTemplate, body_pose: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
    """(T, V, 3) float64 vertices of `template` skinned in float64 by body_pose (T, 24, 3) and transl (T, 3)."""
    transforms = forward_kinematics(body_pose.double(), template.rest_joints.double(), transl.double())
    return skin_points(template.vertices.double(), template.weights.double(), transforms)


def frame_pixels(frame: MeshRender) -> tuple[np.ndarray, np.ndarray]:
    """A render as make_sample stores it: image (H, W, 3) uint8 on white and mask (H, W) bool (coverage >= 0.5)."""
    return np.round(np.clip(frame.rgb, 0.0, 1.0) * 255.0).astype(np.uint8), frame.coverage >= 0.5
