import math

import pytest
import torch

from avatarperfect_cli.avatar.model import Avatar, normal_to_quaternion
from avatarperfect_cli.body import BodyTemplate, axis_angle_to_matrix, quaternion_to_matrix
from avatarperfect_cli.errors import InputFileError
from avatarperfect_cli.gaussians import Gaussians, sh_to_rgb
from avatarperfect_cli.io.ply import read_gaussians, write_gaussians

# Regular octahedron: vertices on the axes, faces counter-clockwise seen from outside.
OCTAHEDRON_VERTICES = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
OCTAHEDRON_FACES = [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]


def octahedron_template(scale: float = 0.1) -> BodyTemplate:
    generator = torch.Generator().manual_seed(0)
    raw = torch.rand(6, 24, generator=generator) * (torch.rand(6, 24, generator=generator) < 0.3)
    raw[:, 0] += 0.1  # every row has some weight
    return BodyTemplate(
        vertices=torch.tensor(OCTAHEDRON_VERTICES, dtype=torch.float32) * scale,
        faces=torch.tensor(OCTAHEDRON_FACES),
        weights=raw / raw.sum(dim=1, keepdim=True),
        rest_joints=torch.randn(24, 3, generator=generator) * 0.2,
    )


def test_faces_point_outwards() -> None:
    v = torch.tensor(OCTAHEDRON_VERTICES, dtype=torch.float32)[torch.tensor(OCTAHEDRON_FACES)]
    normals = torch.linalg.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    assert ((normals * v.mean(dim=1)).sum(-1) > 0).all()


def test_from_template_places_flat_discs_on_the_surface() -> None:
    scale = 0.1
    template = octahedron_template(scale)
    avatar = Avatar.from_template(template, sh_degree=1, base_color=(0.2, 0.4, 0.9), body_model={"name": "test"})
    assert len(avatar) == 6
    torch.testing.assert_close(avatar.params["means"], template.vertices)
    # local z along the outward normal, which for the octahedron is the vertex direction
    local_z = quaternion_to_matrix(avatar.params["quats"])[:, :, 2]
    torch.testing.assert_close(local_z, template.vertices / scale, atol=1e-6, rtol=0)
    # each vertex touches 4 equilateral faces of side sqrt(2) * scale; its share is a third of them
    vertex_area = 4 * (math.sqrt(3) / 4 * 2 * scale**2) / 3
    r = math.sqrt(vertex_area / math.pi)
    torch.testing.assert_close(avatar.scales, torch.tensor([r, r, 0.5 * r]).expand(6, 3))
    torch.testing.assert_close(avatar.opacities, torch.full((6,), 0.99))
    torch.testing.assert_close(sh_to_rgb(avatar.params["sh_dc"][:, 0]), torch.tensor([0.2, 0.4, 0.9]).expand(6, 3))
    assert avatar.params["sh_rest"].shape == (6, 3, 3) and not avatar.params["sh_rest"].any()
    assert avatar.sh.shape == (6, 4, 3)
    torch.testing.assert_close(avatar.skin_weights, template.weights, atol=3e-5, rtol=0)
    assert (avatar.sh_degree, avatar.active_sh_degree) == (1, 0)
    assert all(isinstance(p, torch.nn.Parameter) for p in avatar.params.values())


def test_normal_to_quaternion_turns_z_onto_any_normal() -> None:
    normals = torch.nn.functional.normalize(torch.randn(50, 3, generator=torch.Generator().manual_seed(3)), dim=-1)
    normals = torch.cat([normals, torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])])
    local_z = quaternion_to_matrix(normal_to_quaternion(normals))[:, :, 2]
    torch.testing.assert_close(local_z, normals, atol=1e-6, rtol=0)


def test_pose_with_a_global_rotation_is_rigid() -> None:
    avatar = Avatar.from_template(octahedron_template())
    axis_angle = torch.tensor([0.3, -1.1, 0.4])
    transl = torch.tensor([0.5, -0.2, 2.0])
    body_pose = torch.zeros(24, 3)
    body_pose[0] = axis_angle
    means, quats = avatar.pose(body_pose, transl)
    rotation = axis_angle_to_matrix(axis_angle)
    root = avatar.rest_joints[0]
    expected_means = (avatar.params["means"] - root) @ rotation.T + root + transl
    torch.testing.assert_close(means, expected_means, atol=1e-5, rtol=0)
    expected_rotations = rotation @ quaternion_to_matrix(avatar.params["quats"])
    torch.testing.assert_close(quaternion_to_matrix(quats), expected_rotations, atol=1e-5, rtol=0)


def test_pose_is_differentiable_in_the_skinning_weights() -> None:
    avatar = Avatar.from_template(octahedron_template())
    body_pose = torch.zeros(24, 3)
    body_pose[1:] = 0.3
    means, quats = avatar.pose(body_pose, torch.zeros(3))
    (means.sum() + quats.sum()).backward()
    assert avatar.params["skin_logits"].grad.abs().sum() > 0
    assert avatar.params["means"].grad.abs().sum() > 0


def assert_same_avatar(a: Avatar, b: Avatar, atol: float = 1e-6) -> None:
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        torch.testing.assert_close(a.params[name], b.params[name], atol=atol, rtol=0)
    torch.testing.assert_close(a.skin_weights, b.skin_weights, atol=atol, rtol=0)
    torch.testing.assert_close(a.rest_joints, b.rest_joints, atol=atol, rtol=0)
    assert (a.sh_degree, a.active_sh_degree, a.body_model) == (b.sh_degree, b.active_sh_degree, b.body_model)


def test_gaussians_round_trip() -> None:
    avatar = Avatar.from_template(octahedron_template(), sh_degree=2, body_model={"name": "anny", "age": 0.5})
    avatar.active_sh_degree = 1
    with torch.no_grad():
        avatar.params["sh_rest"].normal_()
        avatar.params["skin_logits"].normal_()
    gaussians = avatar.to_gaussians()
    assert gaussians.extras["skin_weights"].shape == (6, 24)
    assert gaussians.metadata["sh_degree"] == 2
    assert_same_avatar(Avatar.from_gaussians(gaussians), avatar)


def test_ply_round_trip(tmp_path) -> None:
    avatar = Avatar.from_template(octahedron_template(), body_model={"name": "anny", "phenotype": {"age": 0.3}})
    path = tmp_path / "avatar" / "000.ply"
    avatar.save(path)
    assert sorted(p.name for p in path.parent.iterdir()) == ["000.ply"]  # no temporary left behind
    assert read_gaussians(path).extras["skin_weights"].shape == (6, 24)
    assert_same_avatar(Avatar.load(path), avatar)


def test_to_gives_an_independent_copy_with_leaf_parameters() -> None:
    avatar = Avatar.from_template(octahedron_template(), sh_degree=1, body_model={"name": "anny"})
    avatar.active_sh_degree = 1
    moved = avatar.to("cpu")
    assert moved.device == torch.device("cpu") and moved.rest_joints.device == torch.device("cpu")
    assert_same_avatar(moved, avatar)
    for name, param in moved.params.items():
        assert isinstance(param, torch.nn.Parameter) and param.is_leaf and param.requires_grad
        assert param.data_ptr() != avatar.params[name].data_ptr()
    body_pose, transl = 0.3 * torch.randn(24, 3), torch.randn(3)
    for posed, reference in zip(moved.pose(body_pose, transl), avatar.pose(body_pose, transl)):
        assert torch.equal(posed, reference)
    with torch.no_grad():
        moved.params["means"].add_(1.0)
    assert not torch.equal(moved.params["means"], avatar.params["means"])


def test_plain_3dgs_ply_is_a_one_line_input_error(tmp_path) -> None:
    plain = Avatar.from_template(octahedron_template()).to_gaussians()
    path = tmp_path / "plain.ply"
    write_gaussians(path, Gaussians(plain.means, plain.quats, plain.log_scales, plain.opacity_logits, plain.sh))
    with pytest.raises(InputFileError) as error:
        Avatar.load(path)
    message = str(error.value)
    assert str(path) in message and "skin_weights" in message and "\n" not in message


@pytest.mark.parametrize(
    "edit",
    [
        lambda g: g.extras.update(skin_weights=g.extras["skin_weights"][:, :20]),
        lambda g: g.extras.update(skin_weights=g.extras["skin_weights"] * 2),
        lambda g: g.metadata.pop("rest_joints"),
        lambda g: g.metadata.update(rest_joints=[[0.0, 1.0]]),
        lambda g: g.metadata.update(avatar_format=99),
        lambda g: g.metadata.update(sh_degree=3),
        lambda g: g.metadata.update(active_sh_degree=2),
    ],
)
def test_inconsistent_avatar_data_is_an_input_error(edit) -> None:
    gaussians = Avatar.from_template(octahedron_template(), sh_degree=1).to_gaussians()
    edit(gaussians)
    with pytest.raises(InputFileError, match="^bad.ply: "):
        Avatar.from_gaussians(gaussians, source="bad.ply")


def test_set_skin_weights_replaces_the_weights() -> None:
    avatar = Avatar.from_template(octahedron_template())
    weights = torch.softmax(torch.randn(6, 24, generator=torch.Generator().manual_seed(5)), dim=-1)
    avatar.set_skin_weights(weights)
    torch.testing.assert_close(avatar.skin_weights, weights, atol=1e-5, rtol=0)
    assert isinstance(avatar.params["skin_logits"], torch.nn.Parameter)
