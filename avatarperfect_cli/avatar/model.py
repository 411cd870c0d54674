"""The avatar: canonical 3D Gaussians skinned to SMPL's 24-joint skeleton.

Frames and units: the canonical frame is the body template's (SMPL's T-pose, +Y up, metres); `pose`
maps it to the world frame of a body pose and translation.

On disk an avatar is a standard 3DGS PLY (`avatarperfect_cli.io.ply`), so 3DGS viewers open the
canonical avatar, plus the per-Gaussian extra `skin_weights` (N, 24) and this metadata:
    avatar_format     int, AVATAR_FORMAT (what the keys below mean)
    rest_joints       24 x 3 canonical joint positions, metres
    sh_degree         SH degree of the stored coefficients
    active_sh_degree  SH degree rendered so far (training raises it)
    body_model        the body model the template came from, e.g. {"name": "anny", "phenotype": {...}}
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from avatarperfect_cli.body import NUM_JOINTS, BodyTemplate, forward_kinematics, skin_gaussians
from avatarperfect_cli.errors import InputFileError
from avatarperfect_cli.gaussians import Gaussians, num_sh_bases, rgb_to_sh
from avatarperfect_cli.io.ply import read_gaussians, write_gaussians

AVATAR_FORMAT = 1
SKIN_WEIGHTS = "skin_weights"
# Per-Gaussian parameters, each (N, ...); see `Avatar`.
PARAMETER_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest", "skin_logits")

INITIAL_OPACITY = 0.99
# Added to template skinning weights before the log, so zero weights stay learnable.
TEMPLATE_WEIGHT_FLOOR = 1e-6
# Smallest initial disc radius, metres, for template vertices without triangles.
MIN_RADIUS = 1e-4


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def normal_to_quaternion(normals: torch.Tensor) -> torch.Tensor:
    """(N, 4) unit quaternions w x y z of the shortest rotations taking +z to the unit `normals` (N, 3).

    q = normalise(1 + z.n, z x n) = normalise(1 + n_z, -n_y, n_x, 0); for n = -z, a half turn about x.
    """
    nx, ny, nz = normals.unbind(-1)
    quats = torch.stack([1.0 + nz, -ny, nx, torch.zeros_like(nz)], dim=-1)
    flipped = (1.0 + nz) < 1e-6
    half_turn = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=normals.dtype, device=normals.device)
    quats = torch.where(flipped[:, None], half_turn, quats)
    return torch.nn.functional.normalize(quats, dim=-1)


def vertex_normals_and_areas(vertices: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Area-weighted unit vertex normals (V, 3) and vertex areas (V,) (one-ring area / 3), metres^2.

    faces: (F, 3) counter-clockwise seen from outside, so normals point out. A vertex in no triangle
    gets normal +z and area 0.
    """
    corners = vertices[faces]  # (F, 3, 3)
    face_normals = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # 2 * area
    face_areas = 0.5 * face_normals.norm(dim=-1)
    index = faces.reshape(-1)
    normals = torch.zeros_like(vertices).index_add_(0, index, face_normals.repeat_interleave(3, dim=0))
    areas = torch.zeros_like(vertices[:, 0]).index_add_(0, index, face_areas.repeat_interleave(3)) / 3.0
    lengths = normals.norm(dim=-1, keepdim=True)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=vertices.dtype, device=vertices.device)
    normals = torch.where(lengths > 0, normals / lengths.clamp_min(1e-30), up)
    return normals, areas


class Avatar:
    """Canonical Gaussians with per-Gaussian skinning weights over the 24 SMPL joints.

    params (one `torch.nn.Parameter` per name, all with first dimension N; densification replaces
    entries of this dict, so read them through it):
        means           (N, 3) canonical centres, metres
        quats           (N, 4) orientations w x y z, any norm
        log_scales      (N, 3) log standard deviations along the local axes, log metres
        opacity_logits  (N,)   logit opacity
        sh_dc           (N, 1, 3) SH DC coefficients
        sh_rest         (N, K - 1, 3) higher SH bands, K = (sh_degree + 1)^2
        skin_logits     (N, 24) skinning weights = softmax(skin_logits)
    rest_joints:       (24, 3) canonical joint positions, metres
    sh_degree:         SH degree stored; active_sh_degree <= sh_degree is the one rendered
    body_model:        JSON-serialisable description of the template's body model
    """

    def __init__(
        self,
        params: Mapping[str, torch.Tensor],
        rest_joints: torch.Tensor,
        sh_degree: int,
        active_sh_degree: int = 0,
        body_model: dict[str, Any] | None = None,
    ) -> None:
        if set(params) != set(PARAMETER_NAMES):
            raise ValueError(f"avatar parameters must be {PARAMETER_NAMES}, got {tuple(params)}")
        n = params["means"].shape[0]
        bases = num_sh_bases(sh_degree)
        expected = {
            "means": (n, 3),
            "quats": (n, 4),
            "log_scales": (n, 3),
            "opacity_logits": (n,),
            "sh_dc": (n, 1, 3),
            "sh_rest": (n, bases - 1, 3),
            "skin_logits": (n, NUM_JOINTS),
        }
        for name, shape in expected.items():
            if tuple(params[name].shape) != shape:
                raise ValueError(f"{name} has shape {tuple(params[name].shape)}, expected {shape}")
        if tuple(rest_joints.shape) != (NUM_JOINTS, 3):
            raise ValueError(f"rest_joints has shape {tuple(rest_joints.shape)}, expected ({NUM_JOINTS}, 3)")
        if not 0 <= active_sh_degree <= sh_degree:
            raise ValueError(f"active SH degree {active_sh_degree} is not in 0..{sh_degree}")
        self.params: dict[str, torch.nn.Parameter] = {
            name: torch.nn.Parameter(params[name].detach().clone()) for name in PARAMETER_NAMES
        }
        self.rest_joints = rest_joints.detach().clone()
        self.sh_degree = sh_degree
        self.active_sh_degree = active_sh_degree
        self.body_model = dict(body_model or {})

    def __len__(self) -> int:
        return self.params["means"].shape[0]

    @property
    def device(self) -> torch.device:
        """The device every parameter and `rest_joints` live on."""
        return self.params["means"].device

    @property
    def scales(self) -> torch.Tensor:
        """(N, 3) standard deviations, metres."""
        return torch.exp(self.params["log_scales"])

    @property
    def opacities(self) -> torch.Tensor:
        """(N,) opacities in (0, 1)."""
        return torch.sigmoid(self.params["opacity_logits"])

    @property
    def sh(self) -> torch.Tensor:
        """(N, K, 3) all SH coefficients, K = (sh_degree + 1)^2."""
        return torch.cat([self.params["sh_dc"], self.params["sh_rest"]], dim=1)

    @property
    def skin_weights(self) -> torch.Tensor:
        """(N, 24) skinning weights, rows summing to 1."""
        return torch.softmax(self.params["skin_logits"], dim=-1)

    def set_skin_weights(self, weights: torch.Tensor) -> None:
        """Replace the skinning weights by `weights` (N, 24), rows summing to 1 (logits as `from_template`'s)."""
        with torch.no_grad():
            self.params["skin_logits"].copy_(torch.log(weights.to(self.params["skin_logits"]) + TEMPLATE_WEIGHT_FLOOR))

    @classmethod
    def from_template(
        cls,
        template: BodyTemplate,
        sh_degree: int = 1,
        base_color: Sequence[float] = (0.5, 0.5, 0.5),
        normal_scale_ratio: float = 0.5,
        body_model: dict[str, Any] | None = None,
    ) -> Avatar:
        """GART's initialisation: one Gaussian per template vertex.

        Each is a flat disc tangent to the surface: local z along the vertex normal, standard
        deviations (r, r, normal_scale_ratio * r) with r = sqrt(A / pi), A the vertex's area (one-ring
        triangle area / 3, so the discs share the surface), at least MIN_RADIUS; opacity 0.99; colour
        `base_color` (RGB in [0, 1]) in the DC band, higher bands zero; skinning logits
        log(w + 1e-6) from the template weights w. Rendering starts at SH degree 0.
        """
        vertices = template.vertices.detach().float()
        normals, areas = vertex_normals_and_areas(vertices, template.faces.long())
        radii = torch.sqrt(areas / math.pi).clamp_min(MIN_RADIUS)
        n = vertices.shape[0]
        color = torch.as_tensor(base_color, dtype=torch.float32).reshape(1, 1, 3)
        params = {
            "means": vertices,
            "quats": normal_to_quaternion(normals),
            "log_scales": torch.log(radii[:, None] * torch.tensor([1.0, 1.0, normal_scale_ratio])),
            "opacity_logits": torch.full((n,), _logit(INITIAL_OPACITY)),
            "sh_dc": rgb_to_sh(color).expand(n, 1, 3),
            "sh_rest": torch.zeros(n, num_sh_bases(sh_degree) - 1, 3),
            "skin_logits": torch.log(template.weights.detach().float() + TEMPLATE_WEIGHT_FLOOR),
        }
        return cls(params, template.rest_joints.float(), sh_degree, 0, body_model)

    def pose(
        self, body_pose: torch.Tensor, transl: torch.Tensor, world_transform: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Posed Gaussians by linear blend skinning; differentiable w.r.t. the parameters and the pose.

        body_pose: (24, 3) SMPL axis-angle, joint 0 the global orientation; transl: (3,) metres;
        world_transform: optional (4, 4) rigid transform applied after posing (differentiable too).
        The pose tensors may live on any device; they are moved (differentiably) to the avatar's.
        Returns world-frame means (N, 3) and quats (N, 4) w x y z, on the avatar's device.
        """
        return self.skin(self.joint_transforms(body_pose, transl, world_transform))

    def joint_transforms(
        self, body_pose: torch.Tensor, transl: torch.Tensor, world_transform: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(24, 4, 4) joint transforms of a pose (see `pose`) on the avatar's device; they depend on the pose
        and `rest_joints` only, so a caller that poses the avatar alike many times may keep them."""
        body_pose, transl = body_pose.to(self.device), transl.to(self.device)
        transforms = forward_kinematics(body_pose[None], self.rest_joints, transl[None])[0]
        if world_transform is not None:
            transforms = world_transform.to(self.device) @ transforms
        return transforms

    def skin(self, transforms: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World-frame means (N, 3) and quats (N, 4) for `joint_transforms`' (24, 4, 4) result."""
        return skin_gaussians(self.params["means"], self.params["quats"], self.skin_weights, transforms)

    def to(self, device: torch.device | str) -> Avatar:
        """A copy on `device` whose parameters are new leaf `torch.nn.Parameter`s (make optimizers after moving)."""
        moved = {name: param.detach().to(device) for name, param in self.params.items()}
        return Avatar(moved, self.rest_joints.to(device), self.sh_degree, self.active_sh_degree, self.body_model)

    def with_params(self, params: Mapping[str, torch.Tensor]) -> Avatar:
        """A new avatar of the given per-Gaussian parameters (any count; `PARAMETER_NAMES`) with this one's rest
        joints, SH degrees and body model."""
        return Avatar(params, self.rest_joints, self.sh_degree, self.active_sh_degree, self.body_model)

    def to_gaussians(self) -> Gaussians:
        """The canonical avatar as a detached `Gaussians` with the skinning extra and the metadata."""
        p = {name: param.detach() for name, param in self.params.items()}
        return Gaussians(
            means=p["means"],
            quats=p["quats"],
            log_scales=p["log_scales"],
            opacity_logits=p["opacity_logits"],
            sh=torch.cat([p["sh_dc"], p["sh_rest"]], dim=1),
            extras={SKIN_WEIGHTS: torch.softmax(p["skin_logits"], dim=-1)},
            metadata={
                "avatar_format": AVATAR_FORMAT,
                "rest_joints": self.rest_joints.tolist(),
                "sh_degree": self.sh_degree,
                "active_sh_degree": self.active_sh_degree,
                "body_model": self.body_model,
            },
        )

    @classmethod
    def from_gaussians(cls, gaussians: Gaussians, source: object = "avatar") -> Avatar:
        """The avatar stored in `gaussians` (from `to_gaussians` or a PLY).

        Raises InputFileError(source, problem) when the skinning extra or the metadata is missing or
        inconsistent; `source` names the file in that one-line message.
        """
        weights = gaussians.extras.get(SKIN_WEIGHTS)
        if weights is None:
            raise InputFileError(source, f"no '{SKIN_WEIGHTS}' per-Gaussian properties: not an avatarperfect avatar")
        if weights.shape[1] != NUM_JOINTS:
            raise InputFileError(source, f"'{SKIN_WEIGHTS}' has {weights.shape[1]} columns, expected {NUM_JOINTS}")
        if len(gaussians) and ((weights < 0).any() or ((weights.sum(dim=1) - 1).abs() > 1e-3).any()):
            raise InputFileError(source, f"'{SKIN_WEIGHTS}' rows must be non-negative and sum to 1")
        metadata = gaussians.metadata
        version = metadata.get("avatar_format")
        if not isinstance(version, int) or version < 1:
            raise InputFileError(source, "metadata has no valid 'avatar_format': not an avatarperfect avatar")
        if version > AVATAR_FORMAT:
            raise InputFileError(source, f"avatar format {version} is newer than supported ({AVATAR_FORMAT})")
        try:
            rest_joints = torch.tensor(metadata["rest_joints"], dtype=torch.float32)
        except (KeyError, TypeError, ValueError):
            raise InputFileError(source, "metadata 'rest_joints' is missing or not a 24 x 3 list of numbers") from None
        if tuple(rest_joints.shape) != (NUM_JOINTS, 3):
            shape = tuple(rest_joints.shape)
            raise InputFileError(source, f"metadata 'rest_joints' has shape {shape}, expected (24, 3)")
        stored_degree = metadata.get("sh_degree", gaussians.sh_degree)
        if stored_degree != gaussians.sh_degree:
            problem = f"metadata 'sh_degree' {stored_degree!r} does not match {gaussians.sh.shape[1]} SH bases"
            raise InputFileError(source, problem)
        active = metadata.get("active_sh_degree", gaussians.sh_degree)
        if not isinstance(active, int) or not 0 <= active <= gaussians.sh_degree:
            raise InputFileError(source, f"metadata 'active_sh_degree' {active!r} is not in 0..{gaussians.sh_degree}")
        body_model = metadata.get("body_model", {})
        if not isinstance(body_model, dict):
            raise InputFileError(source, "metadata 'body_model' is not a JSON object")
        params = {
            "means": gaussians.means,
            "quats": gaussians.quats,
            "log_scales": gaussians.log_scales,
            "opacity_logits": gaussians.opacity_logits,
            "sh_dc": gaussians.sh[:, :1],
            "sh_rest": gaussians.sh[:, 1:],
            # softmax(log w) = w exactly; the floor only keeps zero weights finite
            "skin_logits": torch.log(weights.clamp_min(torch.finfo(weights.dtype).tiny)),
        }
        return cls(params, rest_joints, gaussians.sh_degree, active, body_model)

    def save(self, path: Path | str) -> None:
        """Write the canonical avatar as a 3DGS PLY with the skinning extra, atomically (from any device)."""
        write_gaussians(path, self.to_gaussians().to("cpu"))

    @classmethod
    def load(cls, path: Path | str) -> Avatar:
        """Read an avatar PLY written by `save`; InputFileError (one line) when unusable."""
        return cls.from_gaussians(read_gaussians(path), source=path)
