"""Natural-pose decoders D(z): a latent z in R^32 -> an SMPL body pose, for pose suggestion (paper §6.2).

Two decoders share the `PosePrior` interface. Both keep joint 0 (global orientation) and the hands (22, 23) at
the reference pose (the pose the avatar was trained in); the camera, not the body, turns the view.

builtin (free): z drives 32 of the body's axis-angle components, each confined to its anatomical range
(`JOINT_LIMITS_DEG`, on the components of SMPL's axis-angle in the canonical frame, like the source table):
    component_k = ref_k + (hi_k - lo_k) * (sigmoid(z_k + b_k) - sigmoid(b_k)),
    b_k = logit((ref_k - lo_k) / (hi_k - lo_k)),
so z = 0 gives exactly the reference, every z stays inside (lo_k, hi_k), and a unit of z_k moves the angle by at
most a quarter of its range: z ~ N(0, I) (`sample_latent`) spreads the angles around the reference without piling
them up at the range ends. A reference outside a range widens that range to include it (plus
`REFERENCE_MARGIN_DEG`). The 32 components (`CONTROLLED_COMPONENTS`; x bends forwards/backwards, y turns about
the vertical, z bends sideways, for arms in the T-pose x twists along the arm, y swings it forwards/backwards,
z raises/lowers it): spine1 x y z, spine3 x y, neck x y z; per side collar y z, shoulder x y z, elbow flexion,
wrist flexion, hip x y z, knee flexion, ankle flexion. The other components stay at the reference.

vposer (licensed, from the user's files): the VPoser v2 decoder (DESIGN.md "Pose prior"): MLP 32 -> 512 -> 512
-> 126, continuous 6D rotations of SMPL joints 1..21.
"""

from __future__ import annotations

import math
import pickle
import types
from pathlib import Path
from typing import Protocol

import torch
import torch.nn.functional as F

from avatarperfect_cli.body import NUM_JOINTS, SMPL_JOINT_NAMES, axis_angle_to_matrix
from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.rotations import matrix_to_axis_angle, rotation_6d_to_matrix

LATENT_DIM = 32
POSE_PRIORS = ("builtin", "vposer")
AXES = "xyz"

# Anatomical ranges, degrees, of the components of each joint's SMPL axis-angle (canonical axes x, y, z; zero is
# the T-pose, arms horizontal along +-X), for the left side and the midline; `_mirrored` gives the right side
# (a mirror in X keeps x and negates y and z). Facts from the per-axis SMPL joint limits of bodies-at-rest
# (Clever et al., CVPR 2020; github.com/Healthcare-Robotics/bodies-at-rest, lib_py/mesh_depth_lib_br.py,
# "axang_limits") and the AAOS normal ranges of motion; the spine, neck, collar, elbow-twist and wrist ranges
# are wider than that table's (it describes bodies lying at rest), the knee's a few degrees of hyperextension.
# Signs, left side: hip x < 0 flexes (leg forwards), z > 0 abducts; knee x > 0 flexes; ankle x > 0 points the
# toes; spine/neck x > 0 bends forwards; collar z > 0 shrugs; shoulder z > 0 raises the arm, y < 0 swings it
# forwards; elbow y < 0 flexes; wrist z < 0 flexes (palm down in the T-pose).
JOINT_LIMITS_DEG: dict[str, tuple[tuple[float, float], tuple[float, float], tuple[float, float]]] = {
    "left_hip": ((-115.0, 15.0), (-35.0, 35.0), (-30.0, 45.0)),
    "spine1": ((-25.0, 60.0), (-15.0, 15.0), (-20.0, 20.0)),
    "left_knee": ((-5.0, 145.0), (-15.0, 15.0), (-5.0, 5.0)),
    "spine2": ((-10.0, 20.0), (-15.0, 15.0), (-10.0, 10.0)),
    "left_ankle": ((-40.0, 50.0), (-30.0, 30.0), (-30.0, 30.0)),
    "spine3": ((-10.0, 20.0), (-15.0, 15.0), (-10.0, 10.0)),
    "left_foot": ((-60.0, 40.0), (-10.0, 10.0), (-10.0, 10.0)),
    "neck": ((-35.0, 40.0), (-45.0, 45.0), (-30.0, 30.0)),
    "left_collar": ((-20.0, 20.0), (-30.0, 25.0), (-20.0, 40.0)),
    "head": ((-25.0, 20.0), (-30.0, 30.0), (-15.0, 15.0)),
    "left_shoulder": ((-80.0, 80.0), (-95.0, 40.0), (-90.0, 70.0)),
    "left_elbow": ((-80.0, 80.0), (-150.0, 5.0), (-15.0, 15.0)),
    "left_wrist": ((-30.0, 30.0), (-20.0, 30.0), (-80.0, 70.0)),
}
# Joints whose ranges are checked: the body joints 1..21 (0 is the global orientation, 22/23 the hands).
LIMITED_JOINTS = range(1, 22)
CONTROLLED_COMPONENTS: tuple[tuple[str, str], ...] = (
    ("spine1", "x"), ("spine1", "y"), ("spine1", "z"), ("spine3", "x"), ("spine3", "y"),
    ("neck", "x"), ("neck", "y"), ("neck", "z"),
    *(
        (f"{side}_{joint}", axis)
        for side in ("left", "right")
        for joint, axes in (
            ("collar", "yz"), ("shoulder", "xyz"), ("elbow", "y"), ("wrist", "z"),
            ("hip", "xyz"), ("knee", "x"), ("ankle", "x"),
        )
        for axis in axes
    ),
)  # fmt: skip
REFERENCE_MARGIN_DEG = 1.0

# VPoser v2's decoder: parameter name -> shape, stored with or without this prefix.
VPOSER_PREFIX = "vp_model."
VPOSER_DECODER_SHAPES: dict[str, tuple[int, ...]] = {
    "decoder_net.0.weight": (512, LATENT_DIM),
    "decoder_net.0.bias": (512,),
    "decoder_net.3.weight": (512, 512),
    "decoder_net.3.bias": (512,),
    "decoder_net.5.weight": (21 * 6, 512),
    "decoder_net.5.bias": (21 * 6,),
}
VPOSER_LEAKY_SLOPE = 0.01  # torch.nn.LeakyReLU's default, which VPoser uses
# The latent that best reproduces the reference pose: Adam from z = 0 on the squared rotation-matrix error.
VPOSER_FIT_STEPS = 300
VPOSER_FIT_LEARNING_RATE = 0.05


class PosePrior(Protocol):
    """A natural-pose decoder. latent_dim: size of z; description: one line naming the prior (and its file)."""

    latent_dim: int
    description: str

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """z: (B, latent_dim) -> body_pose (B, 24, 3) axis-angle, radians, differentiable in z; joint 0 and the
        hands (22, 23) are the reference's."""
        ...

    def initial_latent(self) -> torch.Tensor:
        """(latent_dim,) the z whose decoded pose is (closest to) the reference pose."""
        ...

    def sample_latent(self, generator: torch.Generator) -> torch.Tensor:
        """(latent_dim,) the z of a random natural pose."""
        ...


def _mirrored(limits: tuple[tuple[float, float], ...]) -> tuple[tuple[float, float], ...]:
    """The right side's ranges from the left's: x kept, y and z negated."""
    (x_lo, x_hi), (y_lo, y_hi), (z_lo, z_hi) = limits
    return (x_lo, x_hi), (-y_hi, -y_lo), (-z_hi, -z_lo)


def joint_limits_deg() -> torch.Tensor:
    """(24, 3, 2) float64 [low, high] degrees of every joint's axis-angle components; -inf/inf for joints that
    are not limited (0, 22, 23)."""
    limits = torch.tensor([-math.inf, math.inf], dtype=torch.float64).repeat(NUM_JOINTS, 3, 1)
    for joint in LIMITED_JOINTS:
        name = SMPL_JOINT_NAMES[joint]
        if name in JOINT_LIMITS_DEG:
            limits[joint] = torch.tensor(JOINT_LIMITS_DEG[name], dtype=torch.float64)
        else:
            left = JOINT_LIMITS_DEG[name.replace("right_", "left_")]
            limits[joint] = torch.tensor(_mirrored(left), dtype=torch.float64)
    return limits


def joint_limit_violations(body_pose: torch.Tensor, tolerance_deg: float = 0.5) -> list[str]:
    """body_pose: (24, 3) axis-angle, radians -> one line per component of joints 1..21 outside its anatomical
    range by more than `tolerance_deg` degrees, [] when all are inside."""
    degrees = torch.rad2deg(torch.as_tensor(body_pose, dtype=torch.float64).detach().cpu().reshape(NUM_JOINTS, 3))
    limits = joint_limits_deg()
    outside = (degrees < limits[..., 0] - tolerance_deg) | (degrees > limits[..., 1] + tolerance_deg)
    return [
        f"{SMPL_JOINT_NAMES[joint]} {AXES[axis]} = {degrees[joint, axis]:.1f} deg outside "
        f"[{limits[joint, axis, 0]:g}, {limits[joint, axis, 1]:g}] deg"
        for joint, axis in outside.nonzero().tolist()
    ]


def _reference(reference_pose: torch.Tensor) -> torch.Tensor:
    reference = torch.as_tensor(reference_pose, dtype=torch.float64).detach().cpu()
    if reference.shape != (NUM_JOINTS, 3):
        raise ValueError(f"reference_pose must be ({NUM_JOINTS}, 3), got {tuple(reference.shape)}")
    return reference


def _with_reference(reference: torch.Tensor, joints: slice, values: torch.Tensor) -> torch.Tensor:
    """(B, 24, 3): the reference pose (24, 3) with `joints` replaced by `values` (B, n, 3)."""
    batch = values.shape[0]
    pose = reference.to(dtype=values.dtype, device=values.device).expand(batch, NUM_JOINTS, 3).clone()
    pose[:, joints] = values
    return pose


class BuiltinPosePrior:
    """The free prior: z moves 32 axis-angle components inside their anatomical ranges (see the module doc)."""

    latent_dim = LATENT_DIM
    description = f"builtin joint-limit pose prior ({LATENT_DIM} joint angles)"

    def __init__(self, reference_pose: torch.Tensor) -> None:
        """reference_pose: (24, 3) axis-angle, radians: the pose z = 0 decodes to."""
        self.reference = _reference(reference_pose)
        limits = torch.deg2rad(joint_limits_deg())
        joints = [SMPL_JOINT_NAMES.index(name) for name, _ in CONTROLLED_COMPONENTS]
        axes = [AXES.index(axis) for _, axis in CONTROLLED_COMPONENTS]
        self.flat_indices = torch.tensor([3 * j + a for j, a in zip(joints, axes)], dtype=torch.int64)
        reference_values = self.reference[joints, axes]
        margin = math.radians(REFERENCE_MARGIN_DEG)
        low = torch.minimum(limits[joints, axes, 0], reference_values - margin)
        high = torch.maximum(limits[joints, axes, 1], reference_values + margin)
        self.spans = high - low
        self.offsets = torch.logit((reference_values - low) / self.spans)
        self.reference_values = reference_values

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        if z.ndim != 2 or z.shape[1] != LATENT_DIM:
            raise ValueError(f"z must be (B, {LATENT_DIM}), got {tuple(z.shape)}")
        offsets, spans, values = (
            t.to(dtype=z.dtype, device=z.device) for t in (self.offsets, self.spans, self.reference_values)
        )
        components = values + spans * (torch.sigmoid(z + offsets) - torch.sigmoid(offsets))
        flat = self.reference.to(dtype=z.dtype, device=z.device).reshape(1, -1).repeat(z.shape[0], 1)
        flat[:, self.flat_indices.to(z.device)] = components
        return flat.reshape(-1, NUM_JOINTS, 3)

    def initial_latent(self) -> torch.Tensor:
        return torch.zeros(LATENT_DIM)

    def sample_latent(self, generator: torch.Generator) -> torch.Tensor:
        return torch.randn(LATENT_DIM, generator=generator)


class _Placeholder(dict):
    """Stands in, when unpickling a checkpoint, for a class whose module is not installed."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__()

    def __setstate__(self, state: object) -> None:
        pass


class _TolerantUnpickler(pickle.Unpickler):
    """Unpickles classes it cannot import (training-time extras of Lightning checkpoints) as `_Placeholder`."""

    def find_class(self, module: str, name: str) -> object:
        try:
            return super().find_class(module, name)
        except (ImportError, AttributeError):
            return _Placeholder


# what torch.load's pickle_module needs: Unpickler, load and a name
_TOLERANT_PICKLE = types.ModuleType("tolerant_pickle")
_TOLERANT_PICKLE.Unpickler = _TolerantUnpickler
_TOLERANT_PICKLE.load = lambda file, **kwargs: _TolerantUnpickler(file, **kwargs).load()


def _first_line(error: BaseException) -> str:
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__


def find_vposer_checkpoint(vposer_dir: Path) -> tuple[Path, str]:
    """The checkpoint (*.ckpt, searched recursively) in the user's VPoser folder and a note saying which was taken:
    the last by path name when there are several (VPoser snapshots are named by epoch)."""
    vposer_dir = Path(vposer_dir)
    if not vposer_dir.is_dir():
        raise InputFileError(vposer_dir, "VPoser folder not found")
    checkpoints = sorted((path for path in vposer_dir.rglob("*.ckpt") if path.is_file()), key=lambda p: p.as_posix())
    if not checkpoints:
        raise InputFileError(
            vposer_dir, "no VPoser checkpoint (*.ckpt) in this folder; VPoser v2 keeps it in V02_05/snapshots/"
        )
    chosen = checkpoints[-1]
    note = f" (the last by name of {len(checkpoints)} checkpoints)" if len(checkpoints) > 1 else ""
    return chosen, note


def _load_checkpoint(path: Path) -> object:
    """torch.load on the CPU: weights only first; the user's own file may need full unpickling (Lightning
    checkpoints carry training objects), with classes that are not installed replaced by placeholders."""
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # noqa: BLE001 - any failure of the safe loader means: try the full one
        pass
    try:
        return torch.load(path, map_location="cpu", weights_only=False, pickle_module=_TOLERANT_PICKLE)
    except Exception as error:  # noqa: BLE001 - torch.load raises many types for a bad file
        raise InputFileError(path, f"not a readable PyTorch checkpoint ({_first_line(error)})") from error


def read_vposer_decoder(path: Path) -> dict[str, torch.Tensor]:
    """The VPoser v2 decoder's weights from checkpoint `path`: name (without prefix) -> float32 tensor, shapes as in
    `VPOSER_DECODER_SHAPES`. InputFileError naming the missing or misshapen ones."""
    checkpoint = _load_checkpoint(path)
    state = checkpoint.get("state_dict", checkpoint) if isinstance(checkpoint, dict) else None
    if not isinstance(state, dict):
        raise InputFileError(path, "not a VPoser checkpoint (no state_dict)")
    weights: dict[str, torch.Tensor] = {}
    missing = []
    for name, shape in VPOSER_DECODER_SHAPES.items():
        value = state.get(VPOSER_PREFIX + name, state.get(name))
        if not isinstance(value, torch.Tensor):
            missing.append(name)
            continue
        if tuple(value.shape) != shape:
            raise InputFileError(path, f"VPoser weight {name} has shape {tuple(value.shape)}, expected {shape}")
        weights[name] = value.detach().to(torch.float32)
    if missing:
        raise InputFileError(
            path, f"not a VPoser v2 checkpoint: missing {', '.join(missing)} (with or without {VPOSER_PREFIX!r})"
        )
    return weights


class VPoserPrior:
    """The VPoser v2 decoder (licensed weights from the user's checkpoint) for SMPL joints 1..21."""

    latent_dim = LATENT_DIM

    def __init__(
        self, weights: dict[str, torch.Tensor], reference_pose: torch.Tensor, description: str = "VPoser v2"
    ) -> None:
        """weights: see `read_vposer_decoder`; reference_pose: (24, 3) axis-angle: joints 0, 22, 23 and the pose
        `initial_latent` reproduces."""
        self.weights = weights
        self.reference = _reference(reference_pose)
        self.description = description
        self._initial: torch.Tensor | None = None

    def body_rotations(self, z: torch.Tensor) -> torch.Tensor:
        """z: (B, 32) -> (B, 21, 3, 3) rotations of joints 1..21 (dropout is off: inference)."""
        if z.ndim != 2 or z.shape[1] != LATENT_DIM:
            raise ValueError(f"z must be (B, {LATENT_DIM}), got {tuple(z.shape)}")
        w = {name: value.to(dtype=z.dtype, device=z.device) for name, value in self.weights.items()}
        hidden = F.leaky_relu(F.linear(z, w["decoder_net.0.weight"], w["decoder_net.0.bias"]), VPOSER_LEAKY_SLOPE)
        hidden = F.leaky_relu(F.linear(hidden, w["decoder_net.3.weight"], w["decoder_net.3.bias"]), VPOSER_LEAKY_SLOPE)
        out = F.linear(hidden, w["decoder_net.5.weight"], w["decoder_net.5.bias"])
        return rotation_6d_to_matrix(out.reshape(-1, 21, 3, 2))

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return _with_reference(self.reference, slice(1, 22), matrix_to_axis_angle(self.body_rotations(z)))

    def initial_latent(self) -> torch.Tensor:
        if self._initial is None:
            target = axis_angle_to_matrix(self.reference[1:22].to(torch.float32))
            z = torch.zeros(1, LATENT_DIM, requires_grad=True)
            optimizer = torch.optim.Adam([z], lr=VPOSER_FIT_LEARNING_RATE)
            for _ in range(VPOSER_FIT_STEPS):
                optimizer.zero_grad()
                loss = (self.body_rotations(z)[0] - target).square().sum()
                loss.backward()
                optimizer.step()
            self._initial = z.detach()[0]
        return self._initial.clone()

    def sample_latent(self, generator: torch.Generator) -> torch.Tensor:
        return torch.randn(LATENT_DIM, generator=generator)


def load_pose_prior(name: str, reference_pose: torch.Tensor, vposer_dir: Path | None = None) -> PosePrior:
    """The pose prior `name` ("builtin" or "vposer", which reads the user's `vposer_dir`) around `reference_pose`
    (24, 3) axis-angle, radians."""
    if name == "builtin":
        return BuiltinPosePrior(reference_pose)
    if name == "vposer":
        if vposer_dir is None:
            raise AvatarPerfectError("the vposer pose prior needs the folder of your VPoser v2 files (--vposer-dir)")
        path, note = find_vposer_checkpoint(vposer_dir)
        return VPoserPrior(read_vposer_decoder(path), reference_pose, f"VPoser v2 decoder from {path}{note}")
    raise AvatarPerfectError(f"unknown pose prior {name!r}; choose one of {', '.join(POSE_PRIORS)}")
