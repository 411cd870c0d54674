"""The anny template: SMPL frame and T-pose, weights, caching, and our skinning against anny's own posing.

Uses the shared anny cache (`default_cache_dir()`); the very first run builds it (about 2 minutes).
"""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from avatarperfect_cli.body import load_body_template
from avatarperfect_cli.body.anny_model import (
    ANNY_TO_SMPL,
    anny_pose_parameters,
    bone_joints,
    build_anny_template,
    default_cache_dir,
    full_phenotype,
    load_anny_model,
    load_anny_template,
    t_pose_rotations,
)
from avatarperfect_cli.body.base import NUM_JOINTS, SMPL_JOINT_NAMES, BodyTemplate
from avatarperfect_cli.body.skeleton import forward_kinematics, skin_points
from avatarperfect_cli.errors import AvatarPerfectError

J = {name: index for index, name in enumerate(SMPL_JOINT_NAMES)}


@pytest.fixture(scope="module")
def model():
    return load_anny_model(default_cache_dir())


@pytest.fixture(scope="module")
def template() -> BodyTemplate:
    return load_anny_template()


def test_template_shapes_weights_and_uvs(template: BodyTemplate) -> None:
    vertices = template.vertices.shape[0]
    assert template.vertices.shape == (13718, 3) and template.vertices.dtype == torch.float32
    assert template.faces.shape == (27420, 3) and int(template.faces.max()) == vertices - 1
    assert template.weights.shape == (vertices, NUM_JOINTS) and (template.weights >= 0).all()
    torch.testing.assert_close(template.weights.sum(1), torch.ones(vertices))
    assert template.rest_joints.shape == (NUM_JOINTS, 3)
    assert template.uvs is not None and template.face_uvs is not None
    assert template.face_uvs.shape == template.faces.shape
    assert int(template.face_uvs.max()) < template.uvs.shape[0]
    assert template.uvs.min() >= 0.0 and template.uvs.max() <= 1.0


def test_smpl_frame_and_t_pose(template: BodyTemplate) -> None:
    vertices, joints = template.vertices, template.rest_joints
    height = float(vertices[:, 1].max() - vertices[:, 1].min())
    assert 1.5 < height < 1.9
    # +Y up: head above pelvis above ankles; feet are the lowest vertices
    assert joints[J["head"], 1] > joints[J["pelvis"], 1] + 0.5 > joints[J["left_ankle"], 1] + 0.5
    assert vertices[:, 1].min() < joints[J["left_ankle"], 1]
    # +Z front: the nose tip is the front-most point of the head, on the midline; toes ahead of ankles
    head = vertices[vertices[:, 1] > joints[J["head"], 1]]
    nose = head[head[:, 2].argmax()]
    assert abs(float(nose[0])) < 0.01 and nose[2] > joints[J["head"], 2] + 0.05
    assert (joints[[J["left_foot"], J["right_foot"]], 2] > joints[[J["left_ankle"], J["right_ankle"]], 2] + 0.05).all()
    # +X the body's left
    assert joints[J["left_hip"], 0] > 0.05 and joints[J["right_hip"], 0] < -0.05
    # T-pose: elbows and wrists straight out along +-X at shoulder height
    for side, sign in (("left", 1.0), ("right", -1.0)):
        shoulder = joints[J[f"{side}_shoulder"]]
        for part, reach in (("elbow", 0.2), ("wrist", 0.4)):
            joint = joints[J[f"{side}_{part}"]]
            assert sign * (joint[0] - shoulder[0]) > reach
            assert (joint[1:] - shoulder[1:]).abs().max() < 0.02
    # the hands' vertices reach furthest out
    assert vertices[:, 0].max() > joints[J["left_wrist"], 0] + 0.1


def test_unlisted_bones_follow_their_nearest_mapped_ancestor(model) -> None:
    joints = bone_joints(model.bone_labels, model.bone_parents)
    expected = {
        "root": "pelvis", "pelvis.R": "pelvis", "spine05": "pelvis", "upperleg02.L": "left_hip",
        "lowerleg02.R": "right_knee", "spine03": "spine1", "toe1-2.L": "left_foot", "toe5-3.R": "right_foot",
        "shoulder01.L": "left_collar", "upperarm02.R": "right_shoulder", "lowerarm02.L": "left_elbow",
        "finger1-3.L": "left_hand", "finger4-2.R": "right_hand", "neck03": "neck", "eye.R": "head",
    }  # fmt: skip
    for bone, joint in expected.items():
        assert int(joints[model.bone_labels.index(bone)]) == J[joint], bone


def test_phenotypes_shape_the_body(model) -> None:
    short = build_anny_template(model, full_phenotype({"height": 0.0}))
    tall = build_anny_template(model, full_phenotype({"height": 1.0}))

    def height(template: BodyTemplate) -> float:
        return float(template.vertices[:, 1].max() - template.vertices[:, 1].min())

    assert height(tall) > height(short) + 0.15
    with pytest.raises(AvatarPerfectError, match="unknown anny phenotype"):
        full_phenotype({"hair": 0.5})
    with pytest.raises(AvatarPerfectError, match="outside"):
        full_phenotype({"age": 1.5})


def test_cached_template_loads_without_anny(template: BodyTemplate) -> None:
    """Once cached, a template loads from its .npz without importing anny or warp (fast start-up)."""
    again = load_body_template("anny")
    assert torch.equal(again.vertices, template.vertices) and torch.equal(again.weights, template.weights)
    code = (
        "import sys\n"
        "from avatarperfect_cli.body import load_body_template\n"
        "template = load_body_template('anny')\n"
        "print(template.vertices.shape[0], 'anny' in sys.modules, 'warp' in sys.modules)\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.split() == ["13718", "False", "False"]


def test_our_skinning_matches_anny_posing(model, template: BodyTemplate) -> None:
    """Pose anny's own rig with the SMPL pose (each bone given its joint's world rotation on top of the
    A->T correction), and compare with our skeleton skinning the T-pose template."""
    phenotype = full_phenotype(None)
    rest = model(phenotype_kwargs=phenotype)
    heads = rest["rest_bone_heads"][0]
    joints_of_bones = bone_joints(model.bone_labels, model.bone_parents)
    corrections = t_pose_rotations(heads, model.bone_labels)
    generator = torch.Generator().manual_seed(0)
    body_pose = 0.3 * torch.randn(4, NUM_JOINTS, 3, generator=generator, dtype=torch.float64)
    body_pose[0] = 0.0
    transl = 0.3 * torch.randn(4, 3, generator=generator, dtype=torch.float64)

    transforms = forward_kinematics(body_pose, template.rest_joints.double(), transl)
    ours = skin_points(template.vertices.double(), template.weights.double(), transforms)

    to_smpl = ANNY_TO_SMPL
    world_rotations = to_smpl.T @ transforms[:, :, :3, :3] @ to_smpl @ corrections
    parameters = anny_pose_parameters(rest, joints_of_bones, world_rotations, heads[0] + transl @ to_smpl)
    posed = model(parameters, phenotype_kwargs=phenotype, pose_parameterization="world-orient")
    theirs = posed["vertices"] @ to_smpl.T

    error = (ours - theirs).norm(dim=-1)
    print(f"\nLBS vs anny, metres: zero pose max {error[0].max():.2e}; random poses median "
          f"{error[1:].median():.2e}, p99 {error[1:].quantile(0.99):.2e}, max {error[1:].max():.2e}")  # fmt: skip
    assert error[0].max() < 1e-5
    assert error[1:].median() < 1e-5
    assert error[1:].quantile(0.99) < 0.02
    assert error[1:].max() < 0.04


def test_anny_shape_gradient_matches_finite_differences() -> None:
    from avatarperfect_cli.body.anny_model import anny_shape, default_cache_dir, load_anny_model

    model = load_anny_model(default_cache_dir(), progress=False)
    phenotype = torch.tensor([0.3, 0.6, 0.5, 0.4, 0.7, 0.5], dtype=torch.float64, requires_grad=True)
    direction = torch.randn(24, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    (anny_shape(model, phenotype)[1] * direction).sum().backward()
    step = 1e-4
    for index in (1, 4):  # age and height
        moved = [phenotype.detach().clone() for _ in range(2)]
        moved[0][index] += step
        moved[1][index] -= step
        with torch.no_grad():
            numeric = ((anny_shape(model, moved[0])[1] - anny_shape(model, moved[1])[1]) * direction).sum() / (2 * step)
        assert float(phenotype.grad[index]) == pytest.approx(float(numeric), rel=1e-3, abs=1e-6)


def test_a_batch_of_phenotypes_gives_each_body_as_built_alone() -> None:
    from avatarperfect_cli.body.anny_model import anny_shape, default_cache_dir, load_anny_model

    model = load_anny_model(default_cache_dir(), progress=False)
    bodies = torch.tensor([[0.3, 0.6, 0.5, 0.4, 0.7, 0.5], [0.9, 0.1, 0.8, 0.2, 0.3, 0.6]], dtype=torch.float64)
    with torch.no_grad():
        vertices, joints = anny_shape(model, bodies)
        for index, phenotype in enumerate(bodies):
            alone_vertices, alone_joints = anny_shape(model, phenotype)
            assert alone_vertices.shape == vertices.shape[1:] and alone_joints.shape == (24, 3)
            torch.testing.assert_close(vertices[index], alone_vertices, rtol=0, atol=1e-12)
            torch.testing.assert_close(joints[index], alone_joints, rtol=0, atol=1e-12)
    assert (joints[0] - joints[1]).norm(dim=-1).max() > 0.05  # two different bodies, not one repeated


def test_a_described_skeleton_correction_is_applied_and_checked() -> None:
    from avatarperfect_cli.body import load_body_template, load_described_template
    from avatarperfect_cli.errors import AvatarPerfectError

    offsets = torch.zeros(24, 3)
    offsets[16, 0] = 0.01  # a wider left shoulder
    described = load_described_template({"name": "anny", "bone_offsets": offsets.tolist()})
    plain = load_body_template("anny")
    torch.testing.assert_close(described.rest_joints - plain.rest_joints, plain.with_bone_offsets(offsets).rest_joints - plain.rest_joints)
    assert float(described.rest_joints[20, 0] - plain.rest_joints[20, 0]) == pytest.approx(0.01, abs=1e-6)
    with pytest.raises(AvatarPerfectError, match="bone_offsets"):
        load_described_template({"name": "anny", "bone_offsets": [[0.0, 0.0]]})
