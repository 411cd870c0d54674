"""Procedural pose sequences in SMPL's 24x3 axis-angle format (no motion capture).

Axes are SMPL's canonical frame (+Y up, +Z the body's front, +X the body's left); every joint's rest
frame is aligned with it, so a local rotation about X swings a limb forwards or backwards, one about
Z lifts it sideways. Angles are radians, translations metres. Joint 0 is the global orientation.

Translations leave the feet where they are in the rest pose; `generate.py` grounds them on the mesh.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from avatarperfect_cli.body.base import NUM_JOINTS, SMPL_JOINT_NAMES
from avatarperfect_cli.body.skeleton import matrix_to_quaternion
from avatarperfect_cli.rotations import axis_angle_to_matrix

JOINT = {name: index for index, name in enumerate(SMPL_JOINT_NAMES)}
A_POSE_SHOULDER = 0.85  # radians the shoulders lower the arms from horizontal in the A-pose
A_POSE_COLLAR = 0.1  # radians the collar bones add
A_POSE_LEG_CLOSING = 0.05  # radians each leg turns in from the template's stance in the A-pose
HANGING_SHOULDER = 1.25  # radians below horizontal of relaxed, hanging arms


@dataclass
class Motion:
    """N frames of a body motion.

    body_pose: (N, 24, 3) float64 axis-angle, radians; joint 0 is the global orientation
    transl:    (N, 3) float64 root translation, metres
    """

    body_pose: np.ndarray
    transl: np.ndarray

    def __len__(self) -> int:
        return int(self.body_pose.shape[0])


def with_estimation_noise(motion: Motion, degrees: float, seed: int = 0) -> Motion:
    """`motion` as a pose estimator might report it: independent Gaussian noise on every frame, `degrees`
    (standard deviation) on each joint's three axis-angle components, half that on the root orientation,
    and `degrees` / 2 centimetres on each translation axis (3 degrees: posed joints about 5 cm off)."""
    rng = np.random.default_rng(seed)
    noise = rng.normal(0.0, np.deg2rad(degrees), size=motion.body_pose.shape)
    noise[:, 0] *= 0.5
    transl = motion.transl + rng.normal(0.0, 0.005 * degrees, size=motion.transl.shape)
    return Motion(motion.body_pose + noise, transl)


def concatenate(motions: list[Motion]) -> Motion:
    """The motions one after the other."""
    return Motion(np.concatenate([m.body_pose for m in motions]), np.concatenate([m.transl for m in motions]))


def compose(first: np.ndarray, then: np.ndarray) -> np.ndarray:
    """Axis-angle of the rotation `first` followed by `then` (both (..., 3), broadcast) -> (..., 3),
    with angles in [0, pi]."""
    first_m = axis_angle_to_matrix(torch.as_tensor(first, dtype=torch.float64))
    then_m = axis_angle_to_matrix(torch.as_tensor(then, dtype=torch.float64))
    q = matrix_to_quaternion(then_m @ first_m).numpy()  # w x y z, w >= 0
    sine = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(sine, q[..., :1])
    return q[..., 1:] * np.where(sine > 1e-12, angle / np.maximum(sine, 1e-12), 2.0)


def _axis(axis: str, angle: np.ndarray | float) -> np.ndarray:
    """(..., 3) axis-angle of rotations by `angle` about the canonical axis "x", "y" or "z"."""
    angle = np.asarray(angle, dtype=np.float64)
    out = np.zeros(angle.shape + (3,))
    out[..., "xyz".index(axis)] = angle
    return out


def _rest(frames: int) -> np.ndarray:
    return np.zeros((frames, NUM_JOINTS, 3))


def _set_arms_lowered(pose: np.ndarray, angle: np.ndarray | float, palms_forward: np.ndarray | float = 0.0) -> None:
    """Lower both arms from the T-pose by `angle` (radians below horizontal; negative raises them),
    mostly at the shoulders. `palms_forward` first turns each arm about its own axis (radians; pi/2
    turns the palms, and the arms' undersides, to face the front)."""
    angle = np.asarray(angle, dtype=np.float64)
    collar = np.clip(angle, 0.0, None) * (A_POSE_COLLAR / (A_POSE_SHOULDER + A_POSE_COLLAR))
    twist = _axis("x", -np.broadcast_to(np.asarray(palms_forward, dtype=np.float64), angle.shape))
    pose[:, JOINT["left_collar"]] = _axis("z", -collar)
    pose[:, JOINT["right_collar"]] = _axis("z", collar)
    pose[:, JOINT["left_shoulder"]] = compose(twist, _axis("z", -(angle - collar)))
    pose[:, JOINT["right_shoulder"]] = compose(twist, _axis("z", angle - collar))


def _yaw(frames: int, start_deg: float, end_deg: float) -> np.ndarray:
    """(frames,) radians, evenly from start to end (end included when frames > 1)."""
    return np.deg2rad(np.linspace(start_deg, end_deg, frames))


def turntable(frames: int = 100, seed: int = 0) -> Motion:
    """The training video: the person turns once about the vertical axis in an A-pose (arms ~54 degrees
    below horizontal, legs straight), with a slight sway.

    Frame t faces yaw 360 t / frames degrees (frame 0 faces the +Z camera). The sway (a few degrees in
    spine, head and arms, a centimetre of hip shift) has seed-dependent phases.
    """
    rng = np.random.default_rng(seed)
    phases = rng.uniform(0.0, 2.0 * np.pi, size=6)
    t = np.arange(frames) / max(frames, 1)
    wave = [np.sin(2.0 * np.pi * cycles * t + phase) for cycles, phase in zip((3, 2, 4, 3, 5, 2), phases)]
    pose = _rest(frames)
    _set_arms_lowered(pose, A_POSE_SHOULDER + A_POSE_COLLAR + np.deg2rad(4.0) * wave[0])
    pose[:, JOINT["spine1"]] = _axis("x", np.deg2rad(1.5) * wave[1]) + _axis("z", np.deg2rad(1.5) * wave[2])
    pose[:, JOINT["spine3"]] = _axis("z", np.deg2rad(1.0) * wave[2])
    pose[:, JOINT["head"]] = _axis("y", np.deg2rad(5.0) * wave[3]) + _axis("x", np.deg2rad(3.0) * wave[4])
    pose[:, JOINT["left_elbow"]] = _axis("y", -np.deg2rad(6.0) - np.deg2rad(3.0) * wave[5])
    pose[:, JOINT["right_elbow"]] = _axis("y", np.deg2rad(6.0) + np.deg2rad(3.0) * wave[5])
    pose[:, JOINT["left_hip"]] = _axis("z", -A_POSE_LEG_CLOSING)
    pose[:, JOINT["right_hip"]] = _axis("z", A_POSE_LEG_CLOSING)
    pose[:, JOINT["left_ankle"]] = _axis("z", A_POSE_LEG_CLOSING)
    pose[:, JOINT["right_ankle"]] = _axis("z", -A_POSE_LEG_CLOSING)
    pose[:, JOINT["pelvis"]] = _axis("y", 2.0 * np.pi * t)
    transl = np.zeros((frames, 3))
    transl[:, 0] = 0.01 * wave[1]
    return Motion(pose, transl)


def _face(motion: Motion, yaw: np.ndarray) -> Motion:
    """Turn every frame of `motion` (poses and translations) by `yaw` (frames,) radians about +Y."""
    pose = motion.body_pose.copy()
    pose[:, 0] = compose(pose[:, 0], _axis("y", yaw))
    cos, sin = np.cos(yaw), np.sin(yaw)
    x, z = motion.transl[:, 0], motion.transl[:, 2]
    transl = np.stack([cos * x + sin * z, motion.transl[:, 1], -sin * x + cos * z], axis=1)
    return Motion(pose, transl)


def walk(frames: int, yaw_start_deg: float = 0.0, yaw_end_deg: float = 0.0, stride: float = 0.6) -> Motion:
    """One gait cycle: legs and opposite arms swing, knees bend in swing; travels `stride` metres forward,
    centred on the origin, while facing from yaw_start to yaw_end degrees."""
    phase = 2.0 * np.pi * np.arange(frames) / max(frames, 1)
    swing = np.sin(phase)
    pose = _rest(frames)
    for side, sign in (("left", 1.0), ("right", -1.0)):
        leg = sign * swing  # > 0: this leg is forward
        pose[:, JOINT[f"{side}_hip"]] = _axis("x", -0.45 * leg)
        # The knee bends most in mid-swing, while the leg moves forward under the body.
        pose[:, JOINT[f"{side}_knee"]] = _axis("x", 0.1 + 0.55 * np.clip(sign * np.cos(phase), 0.0, None))
        pose[:, JOINT[f"{side}_ankle"]] = _axis("x", -0.15 * leg)
        lower = _axis("z", -sign * HANGING_SHOULDER * np.ones(frames))
        pose[:, JOINT[f"{side}_shoulder"]] = compose(lower, _axis("x", 0.4 * leg))
        pose[:, JOINT[f"{side}_elbow"]] = _axis("y", -sign * (0.25 + 0.15 * np.clip(-leg, 0, None)))
    pose[:, JOINT["spine1"]] = _axis("y", 0.08 * swing)
    transl = np.zeros((frames, 3))
    transl[:, 2] = stride * (np.arange(frames) / max(frames - 1, 1) - 0.5)
    return _face(Motion(pose, transl), _yaw(frames, yaw_start_deg, yaw_end_deg))


def raise_arms(frames: int, yaw_start_deg: float = 0.0, yaw_end_deg: float = 0.0) -> Motion:
    """Arms rise sideways, palms turning forward, from hanging to overhead and back to horizontal:
    the armpits and the inner arms face the front."""
    t = np.linspace(0.0, 1.0, frames)
    # -HANGING_SHOULDER (down) -> +1.2 (overhead) at t = 0.6 -> 0 (T-pose) at the end.
    lift = np.interp(t, [0.0, 0.6, 1.0], [-HANGING_SHOULDER, 1.2, 0.0])
    pose = _rest(frames)
    _set_arms_lowered(pose, -lift, palms_forward=np.interp(t, [0.0, 0.4, 1.0], [0.0, 1.4, 1.4]))
    pose[:, JOINT["left_wrist"]] = _axis("x", 0.3 * np.sin(np.pi * t))
    pose[:, JOINT["right_wrist"]] = _axis("x", 0.3 * np.sin(np.pi * t))
    pose[:, JOINT["head"]] = _axis("x", -0.15 * np.sin(np.pi * t))
    return _face(Motion(pose, np.zeros((frames, 3))), _yaw(frames, yaw_start_deg, yaw_end_deg))


def legs_apart(frames: int, yaw_start_deg: float = 0.0, yaw_end_deg: float = 0.0) -> Motion:
    """A wide stance opening to ~35 degrees per leg, arms out to the sides with the palms forward:
    crotch, inner thighs and inner arms show."""
    t = np.linspace(0.0, 1.0, frames)
    spread = 0.6 * np.sin(0.5 * np.pi * np.clip(1.3 * t, 0.0, 1.0))
    pose = _rest(frames)
    pose[:, JOINT["left_hip"]] = _axis("z", spread)
    pose[:, JOINT["right_hip"]] = _axis("z", -spread)
    pose[:, JOINT["left_ankle"]] = _axis("z", -0.6 * spread)
    pose[:, JOINT["right_ankle"]] = _axis("z", 0.6 * spread)
    _set_arms_lowered(pose, 0.3 - 0.2 * t, palms_forward=1.2 * t)
    return _face(Motion(pose, np.zeros((frames, 3))), _yaw(frames, yaw_start_deg, yaw_end_deg))


def squat(frames: int, yaw_start_deg: float = 0.0, yaw_end_deg: float = 0.0) -> Motion:
    """Down into a squat, knees wide and arms reaching forward, leaning the torso, then partly up again."""
    t = np.linspace(0.0, 1.0, frames)
    depth = np.sin(np.pi * np.clip(t / 0.85, 0.0, 1.0) * 0.5) ** 2
    depth = np.where(t > 0.7, depth * (1.0 - 0.6 * (t - 0.7) / 0.3), depth)
    hip, knee = 1.45 * depth, 2.1 * depth
    pose = _rest(frames)
    for side, sign in (("left", 1.0), ("right", -1.0)):
        pose[:, JOINT[f"{side}_hip"]] = compose(_axis("x", -hip), _axis("z", sign * 0.45 * depth))
        pose[:, JOINT[f"{side}_knee"]] = _axis("x", knee)
        pose[:, JOINT[f"{side}_ankle"]] = _axis("x", hip - knee)  # feet stay flat
        hanging = _axis("z", -sign * HANGING_SHOULDER * np.ones(frames))
        pose[:, JOINT[f"{side}_shoulder"]] = compose(hanging, _axis("x", -1.2 * depth))
    pose[:, JOINT["spine1"]] = _axis("x", 0.35 * depth)
    pose[:, JOINT["spine2"]] = _axis("x", 0.15 * depth)
    return _face(Motion(pose, np.zeros((frames, 3))), _yaw(frames, yaw_start_deg, yaw_end_deg))


def held_out_motion(frames: int = 30) -> Motion:
    """The held-out video: walking, raising the arms, legs apart and a squat, each seen from turning views."""
    parts = np.array_split(np.arange(frames), 4)
    return concatenate(
        [
            walk(len(parts[0]), 40.0, 130.0),
            raise_arms(len(parts[1]), 40.0, -70.0),
            legs_apart(len(parts[2]), 35.0, -35.0),
            squat(len(parts[3]), -150.0, 20.0),
        ]
    )
