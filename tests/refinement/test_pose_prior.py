"""Pose priors: the builtin joint-limit decoder and the VPoser v2 decoder against independent references."""

from __future__ import annotations

import math
import sys
import types
from pathlib import Path

import pytest
import torch

from avatarperfect_cli.body import SMPL_JOINT_NAMES, axis_angle_to_matrix
from avatarperfect_cli.errors import AvatarPerfectError, InputFileError
from avatarperfect_cli.refinement.pose_prior import (
    CONTROLLED_COMPONENTS,
    LATENT_DIM,
    BuiltinPosePrior,
    joint_limit_violations,
    joint_limits_deg,
    load_pose_prior,
)
from avatarperfect_cli.sample.motions import turntable

JOINT = {name: index for index, name in enumerate(SMPL_JOINT_NAMES)}
DECODER_SHAPES = {0: (512, 32), 3: (512, 512), 5: (126, 512)}


@pytest.fixture(scope="module")
def reference() -> torch.Tensor:
    """The sample video's first-frame A-pose, (24, 3) float64."""
    return torch.as_tensor(turntable(1).body_pose[0])


def _controlled() -> tuple[list[int], list[int]]:
    return [JOINT[name] for name, _ in CONTROLLED_COMPONENTS], ["xyz".index(axis) for _, axis in CONTROLLED_COMPONENTS]


# ---------------------------------------------------------------- builtin


def test_builtin_zero_latent_decodes_exactly_to_the_reference(reference: torch.Tensor) -> None:
    prior = load_pose_prior("builtin", reference)
    assert isinstance(prior, BuiltinPosePrior) and prior.latent_dim == LATENT_DIM == len(CONTROLLED_COMPONENTS)
    assert len(set(CONTROLLED_COMPONENTS)) == LATENT_DIM
    decoded = prior.decode(prior.initial_latent()[None].double())[0]
    assert torch.equal(decoded, reference)
    assert joint_limit_violations(reference) == []


def test_builtin_every_latent_stays_inside_the_limits(reference: torch.Tensor) -> None:
    prior = BuiltinPosePrior(reference)
    generator = torch.Generator().manual_seed(0)
    scales = torch.tensor([0.5, 1.0, 3.0, 10.0, 50.0]).repeat_interleave(196)[:, None]
    z = torch.cat([torch.randn(980, LATENT_DIM, generator=generator) * scales, torch.full((10, LATENT_DIM), 50.0),
                   torch.full((10, LATENT_DIM), -50.0)]).double()  # fmt: skip
    poses = prior.decode(z)
    assert all(joint_limit_violations(pose) == [] for pose in poses)
    # only the controlled components move, and huge latents reach (not pass) the ends of the ranges
    joints, axes = _controlled()
    moved = torch.zeros(24, 3, dtype=torch.bool)
    moved[joints, axes] = True
    assert torch.equal(poses[:, ~moved], reference[~moved].expand(len(z), -1))
    limits = torch.deg2rad(joint_limits_deg()[joints, axes])
    assert torch.allclose(poses[-20:-10][:, joints, axes], limits[:, 1].expand(10, -1), atol=1e-9)
    assert torch.allclose(poses[-10:][:, joints, axes], limits[:, 0].expand(10, -1), atol=1e-9)


def test_builtin_decode_gradient_matches_finite_differences(reference: torch.Tensor) -> None:
    prior = BuiltinPosePrior(reference)
    z = torch.randn(2, LATENT_DIM, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    assert torch.autograd.gradcheck(prior.decode, (z.requires_grad_(),))


def test_builtin_samples_are_natural(reference: torch.Tensor) -> None:
    """Random latents spread the angles around the reference without piling them up at the range ends."""
    prior = BuiltinPosePrior(reference)
    z = torch.stack([prior.sample_latent(torch.Generator().manual_seed(seed)) for seed in range(200)])
    assert torch.equal(z[3], prior.sample_latent(torch.Generator().manual_seed(3)))
    joints, axes = _controlled()
    limits = torch.deg2rad(joint_limits_deg()[joints, axes])
    values = prior.decode(z.double())[:, joints, axes]
    position = (values - limits[:, 0]) / (limits[:, 1] - limits[:, 0])
    near_an_end = ((position < 0.03) | (position > 0.97)).double().mean()
    assert near_an_end < 0.1
    assert (values.std(0) > math.radians(2.0)).all()  # every controlled angle does vary


def test_builtin_reference_outside_a_range_widens_it(reference: torch.Tensor) -> None:
    bent = reference.clone()
    bent[JOINT["left_knee"], 0] = math.radians(-20.0)  # hyperextended beyond the -5 degree limit
    prior = BuiltinPosePrior(bent)
    assert torch.equal(prior.decode(torch.zeros(1, LATENT_DIM, dtype=torch.float64))[0], bent)
    assert torch.isfinite(prior.decode(torch.randn(4, LATENT_DIM, dtype=torch.float64))).all()


def test_joint_limit_violations_flags_impossible_joints(reference: torch.Tensor) -> None:
    cases = {
        ("left_elbow", 1, 40.0): "left_elbow y",  # bent backwards (flexion is negative y on the left)
        ("right_elbow", 1, -40.0): "right_elbow y",
        ("left_shoulder", 2, 100.0): "left_shoulder z",  # raised past its range
        ("right_shoulder", 2, -100.0): "right_shoulder z",
        ("left_knee", 0, -30.0): "left_knee x",
    }
    for (joint, axis, degrees), expected in cases.items():
        pose = reference.clone()
        pose[JOINT[joint], axis] = math.radians(degrees)
        found = joint_limit_violations(pose)
        assert len(found) == 1 and found[0].startswith(expected), found
    # the same angles bent the anatomical way are fine
    pose = reference.clone()
    pose[JOINT["left_elbow"], 1], pose[JOINT["right_elbow"], 1] = math.radians(-100.0), math.radians(100.0)
    assert joint_limit_violations(pose) == []


def test_joint_limits_are_mirror_symmetric() -> None:
    """A pose inside the limits mirrored left<->right (x kept, y and z negated) is inside them too."""
    limits = torch.deg2rad(joint_limits_deg()[1:22])
    generator = torch.Generator().manual_seed(2)
    mirror_of = [SMPL_JOINT_NAMES.index(n.replace("left_", "@").replace("right_", "left_").replace("@", "right_"))
                 for n in SMPL_JOINT_NAMES]  # fmt: skip
    for _ in range(50):
        pose = torch.zeros(24, 3, dtype=torch.float64)
        fraction = torch.rand(21, 3, generator=generator, dtype=torch.float64)
        pose[1:22] = limits[..., 0] + fraction * (limits[..., 1] - limits[..., 0])
        mirrored = pose[mirror_of] * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)
        assert joint_limit_violations(pose) == [] and joint_limit_violations(mirrored) == []


# ---------------------------------------------------------------- VPoser


def _random_decoder(seed: int = 5) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    weights = {}
    for layer, shape in DECODER_SHAPES.items():
        weights[f"decoder_net.{layer}.weight"] = torch.randn(shape, generator=generator) / math.sqrt(shape[1])
        weights[f"decoder_net.{layer}.bias"] = 0.1 * torch.randn(shape[0], generator=generator)
    return weights


def _write_checkpoint(path: Path, weights: dict[str, torch.Tensor], prefix: str = "vp_model.", **extra: object) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {prefix + name: value for name, value in weights.items()}
    state["vp_model.encoder_net.0.weight"] = torch.zeros(3)  # other keys a real checkpoint also holds
    torch.save({"epoch": 8, "state_dict": state, **extra}, path)
    return path


def _independent_rotations(weights: dict[str, torch.Tensor], z: torch.Tensor) -> torch.Tensor:
    """VPoser's layer layout as torch modules, then Gram-Schmidt written out per column: (B, 21, 3, 3)."""
    network = torch.nn.Sequential(
        torch.nn.Linear(32, 512), torch.nn.LeakyReLU(), torch.nn.Dropout(0.1),
        torch.nn.Linear(512, 512), torch.nn.LeakyReLU(), torch.nn.Linear(512, 126),
    ).double().eval()  # fmt: skip
    network.load_state_dict({name.removeprefix("decoder_net."): value.double() for name, value in weights.items()})
    with torch.no_grad():
        raw = network(z).reshape(-1, 21, 3, 2)
    a, b = raw[..., 0], raw[..., 1]
    e1 = a / a.norm(dim=-1, keepdim=True)
    u2 = b - (e1 * b).sum(-1, keepdim=True) * e1
    e2 = u2 / u2.norm(dim=-1, keepdim=True)
    (x1, y1, z1), (x2, y2, z2) = e1.unbind(-1), e2.unbind(-1)
    e3 = torch.stack([y1 * z2 - z1 * y2, z1 * x2 - x1 * z2, x1 * y2 - y1 * x2], -1)
    return torch.stack([e1, e2, e3], dim=-1)


@pytest.mark.parametrize("prefix", ["vp_model.", ""])
def test_vposer_checkpoint_decodes_like_an_independent_network(
    tmp_path: Path, reference: torch.Tensor, prefix: str
) -> None:
    weights = _random_decoder()
    path = tmp_path / "V02_05" / "snapshots" / "V02_05_epoch=08_val_loss=0.03.ckpt"
    checkpoint = _write_checkpoint(path, weights, prefix)
    prior = load_pose_prior("vposer", reference, vposer_dir=tmp_path)
    assert prior.latent_dim == LATENT_DIM and str(checkpoint) in prior.description
    z = torch.randn(6, LATENT_DIM, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    poses = prior.decode(z)
    assert poses.shape == (6, 24, 3) and poses.dtype == torch.float64
    assert torch.allclose(axis_angle_to_matrix(poses[:, 1:22]), _independent_rotations(weights, z), atol=1e-10)
    for joint in (0, 22, 23):
        assert torch.equal(poses[:, joint], reference[joint].expand(6, 3))
    assert torch.allclose(poses, load_pose_prior("vposer", reference, vposer_dir=tmp_path).decode(z))


def test_vposer_decode_is_differentiable_and_the_initial_latent_fits_the_reference(
    tmp_path: Path, reference: torch.Tensor
) -> None:
    _write_checkpoint(tmp_path / "vposer.ckpt", _random_decoder())
    prior = load_pose_prior("vposer", reference, vposer_dir=tmp_path)
    z = torch.randn(1, LATENT_DIM, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    assert torch.autograd.gradcheck(prior.decode, (z.requires_grad_(),))

    # a reference the decoder can reproduce: the fitted latent must find it
    target_latent = 0.5 * torch.randn(1, LATENT_DIM, generator=torch.Generator().manual_seed(0))
    reachable = prior.decode(target_latent)[0].double()
    fitted = load_pose_prior("vposer", reachable, vposer_dir=tmp_path)

    def rotation_error(latent: torch.Tensor) -> float:
        decoded = axis_angle_to_matrix(fitted.decode(latent[None].double())[0, 1:22])
        return float((decoded - axis_angle_to_matrix(reachable[1:22])).square().sum())

    initial = fitted.initial_latent()
    assert initial.shape == (LATENT_DIM,) and torch.equal(initial, fitted.initial_latent())
    assert rotation_error(initial) < 0.01 * rotation_error(torch.zeros(LATENT_DIM))
    again = load_pose_prior("vposer", reachable, vposer_dir=tmp_path).initial_latent()
    assert torch.equal(initial, again)  # deterministic
    sample = prior.sample_latent(torch.Generator().manual_seed(8))
    assert sample.shape == (LATENT_DIM,) and torch.equal(sample, prior.sample_latent(torch.Generator().manual_seed(8)))


def test_vposer_picks_the_last_checkpoint_by_name(tmp_path: Path, reference: torch.Tensor) -> None:
    _write_checkpoint(tmp_path / "snapshots" / "V02_05_epoch=08.ckpt", _random_decoder(1))
    last = _write_checkpoint(tmp_path / "snapshots" / "V02_05_epoch=13.ckpt", _random_decoder(2))
    prior = load_pose_prior("vposer", reference, vposer_dir=tmp_path)
    assert str(last) in prior.description and "2 checkpoints" in prior.description
    z = torch.randn(2, LATENT_DIM, dtype=torch.float64)
    expected = _independent_rotations(_random_decoder(2), z)
    assert torch.allclose(axis_angle_to_matrix(prior.decode(z)[:, 1:22]), expected, atol=1e-10)


def test_vposer_reads_lightning_checkpoints_with_classes_that_are_not_installed(
    tmp_path: Path, reference: torch.Tensor
) -> None:
    module = types.ModuleType("training_only_module")

    class TrainingConfig:
        def __init__(self) -> None:
            self.batch_size = 128

    TrainingConfig.__module__, TrainingConfig.__qualname__ = module.__name__, "TrainingConfig"
    module.TrainingConfig = TrainingConfig
    sys.modules[module.__name__] = module
    try:
        _write_checkpoint(tmp_path / "vposer.ckpt", _random_decoder(), hyper_parameters=TrainingConfig())
    finally:
        del sys.modules[module.__name__]
    prior = load_pose_prior("vposer", reference, vposer_dir=tmp_path)
    z = torch.zeros(1, LATENT_DIM, dtype=torch.float64)
    expected = _independent_rotations(_random_decoder(), z)
    assert torch.allclose(axis_angle_to_matrix(prior.decode(z)[:, 1:22]), expected, atol=1e-10)


def _one_line_error(error: pytest.ExceptionInfo) -> str:
    message = str(error.value)
    assert "\n" not in message and message
    return message


def test_vposer_bad_folders_and_checkpoints_raise_one_line_errors(tmp_path: Path, reference: torch.Tensor) -> None:
    with pytest.raises(InputFileError) as error:
        load_pose_prior("vposer", reference, vposer_dir=tmp_path / "nowhere")
    assert "not found" in _one_line_error(error)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputFileError) as error:
        load_pose_prior("vposer", reference, vposer_dir=tmp_path / "empty")
    assert "*.ckpt" in _one_line_error(error)

    weights = _random_decoder()
    incomplete = {name: value for name, value in weights.items() if name != "decoder_net.3.bias"}
    _write_checkpoint(tmp_path / "missing" / "a.ckpt", incomplete)
    with pytest.raises(InputFileError) as error:
        load_pose_prior("vposer", reference, vposer_dir=tmp_path / "missing")
    message = _one_line_error(error)
    assert "decoder_net.3.bias" in message and "decoder_net.0.weight" not in message

    misshapen = dict(weights, **{"decoder_net.5.weight": torch.zeros(120, 512)})
    _write_checkpoint(tmp_path / "shape" / "a.ckpt", misshapen)
    with pytest.raises(InputFileError) as error:
        load_pose_prior("vposer", reference, vposer_dir=tmp_path / "shape")
    assert "decoder_net.5.weight" in _one_line_error(error) and "(120, 512)" in str(error.value)

    (tmp_path / "garbage").mkdir()
    (tmp_path / "garbage" / "a.ckpt").write_bytes(b"not a checkpoint\n" * 10)
    with pytest.raises(InputFileError) as error:
        load_pose_prior("vposer", reference, vposer_dir=tmp_path / "garbage")
    assert "a.ckpt" in _one_line_error(error)

    (tmp_path / "tensor").mkdir()
    torch.save(torch.zeros(3), tmp_path / "tensor" / "a.ckpt")
    with pytest.raises(InputFileError) as error:
        load_pose_prior("vposer", reference, vposer_dir=tmp_path / "tensor")
    assert "state_dict" in _one_line_error(error)


def test_load_pose_prior_rejects_unknown_names_and_a_missing_folder(reference: torch.Tensor) -> None:
    with pytest.raises(AvatarPerfectError, match="builtin, vposer"):
        load_pose_prior("gmm", reference)
    with pytest.raises(AvatarPerfectError, match="--vposer-dir"):
        load_pose_prior("vposer", reference)
