"""SMPL kinematics and skinning against independent float64 references."""

from __future__ import annotations

import pytest
import torch

from avatarperfect_cli.body.base import NUM_JOINTS, SMPL_PARENTS
from avatarperfect_cli.body.skeleton import forward_kinematics, matrix_to_quaternion, skin_gaussians, skin_points
from avatarperfect_cli.rotations import axis_angle_to_matrix, quaternion_to_matrix


def _skew(v: torch.Tensor) -> torch.Tensor:
    m = torch.zeros(v.shape[:-1] + (3, 3), dtype=v.dtype)
    m[..., 0, 1], m[..., 0, 2], m[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    return m - m.transpose(-1, -2)


def _rest_joints(generator: torch.Generator) -> torch.Tensor:
    """A plausible skeleton: each joint a short random offset from its parent."""
    joints = torch.zeros(NUM_JOINTS, 3, dtype=torch.float64)
    joints[0] = torch.tensor([0.0, 0.9, 0.0], dtype=torch.float64)
    for joint, parent in enumerate(SMPL_PARENTS[1:], start=1):
        joints[joint] = joints[parent] + 0.15 * torch.randn(3, generator=generator, dtype=torch.float64)
    return joints


def _sparse_weights(n: int, generator: torch.Generator, per_point: int = 3) -> torch.Tensor:
    weights = torch.zeros(n, NUM_JOINTS, dtype=torch.float64)
    joints = torch.randint(0, NUM_JOINTS, (n, per_point), generator=generator)
    weights.scatter_add_(1, joints, torch.rand(n, per_point, generator=generator, dtype=torch.float64) + 0.1)
    return weights / weights.sum(1, keepdim=True)


def _bone_weights(n: int, generator: torch.Generator) -> torch.Tensor:
    """Like a body's skin: each point weighted between one joint and its parent."""
    joints = torch.randint(1, NUM_JOINTS, (n,), generator=generator)
    share = torch.rand(n, generator=generator, dtype=torch.float64)
    weights = torch.zeros(n, NUM_JOINTS, dtype=torch.float64)
    weights[torch.arange(n), joints] = share
    weights[torch.arange(n), torch.tensor(SMPL_PARENTS)[joints]] = 1.0 - share
    return weights


def _reference_kinematics(body_pose: torch.Tensor, rest_joints: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
    """Per-joint recursion on 4x4 matrices: G_j = G_parent [R_j | J_j - J_parent], A_j = G_j [I | J_j]^-1,
    with R_j = exp([pose_j]x) by the matrix exponential."""
    batch = body_pose.shape[0]
    result = torch.zeros(batch, NUM_JOINTS, 4, 4, dtype=torch.float64)
    for b in range(batch):
        world: list[torch.Tensor] = []
        for joint, parent in enumerate(SMPL_PARENTS):
            local = torch.eye(4, dtype=torch.float64)
            local[:3, :3] = torch.linalg.matrix_exp(_skew(body_pose[b, joint]))
            if parent < 0:
                local[:3, 3] = rest_joints[joint] + transl[b]
                world.append(local)
            else:
                local[:3, 3] = rest_joints[joint] - rest_joints[parent]
                world.append(world[parent] @ local)
            rest = torch.eye(4, dtype=torch.float64)
            rest[:3, 3] = rest_joints[joint]
            result[b, joint] = world[joint] @ torch.linalg.inv(rest)
    return result


def _subtree(joint: int) -> set[int]:
    members = {joint}
    for child, parent in enumerate(SMPL_PARENTS):
        if parent in members:
            members.add(child)
    return members


def test_forward_kinematics_matches_recursive_reference() -> None:
    generator = torch.Generator().manual_seed(2)
    joints = _rest_joints(generator)
    pose = 0.6 * torch.randn(3, NUM_JOINTS, 3, generator=generator, dtype=torch.float64)
    transl = torch.randn(3, 3, generator=generator, dtype=torch.float64)
    torch.testing.assert_close(forward_kinematics(pose, joints, transl), _reference_kinematics(pose, joints, transl))


def test_identity_pose_leaves_points_and_gaussians_unchanged() -> None:
    generator = torch.Generator().manual_seed(3)
    joints = _rest_joints(generator).float()
    transforms = forward_kinematics(torch.zeros(1, NUM_JOINTS, 3), joints, torch.zeros(1, 3))
    assert torch.equal(transforms, torch.eye(4).expand(1, NUM_JOINTS, 4, 4))
    points = torch.randn(50, 3, generator=generator)
    quats = torch.randn(50, 4, generator=generator)
    weights = _sparse_weights(50, generator).float()
    torch.testing.assert_close(skin_points(points, weights, transforms)[0], points)
    means, posed_quats = skin_gaussians(points, quats, weights, transforms[0])
    torch.testing.assert_close(means, points)
    torch.testing.assert_close(posed_quats, quats)


@pytest.mark.parametrize("joint", [4, 9, 18])
def test_rotating_a_joint_moves_only_its_subtree(joint: int) -> None:
    generator = torch.Generator().manual_seed(4)
    joints = _rest_joints(generator)
    weights = _bone_weights(400, generator)
    points = weights @ joints + 0.05 * torch.randn(400, 3, generator=generator, dtype=torch.float64)
    quats = torch.randn(400, 4, generator=generator, dtype=torch.float64)
    pose = torch.zeros(1, NUM_JOINTS, 3, dtype=torch.float64)
    pose[0, joint] = torch.tensor([0.7, -0.4, 0.3], dtype=torch.float64)
    posed_transforms = forward_kinematics(pose, joints, torch.zeros(1, 3, dtype=torch.float64))
    rest_transforms = forward_kinematics(torch.zeros_like(pose), joints, torch.zeros(1, 3, dtype=torch.float64))

    in_subtree = torch.zeros(NUM_JOINTS, dtype=torch.bool)
    in_subtree[list(_subtree(joint))] = True
    outside = (weights[:, in_subtree] == 0).all(1)
    inside = (weights[:, ~in_subtree] == 0).all(1)
    assert outside.sum() > 50 and inside.sum() > 5

    posed = skin_points(points, weights, posed_transforms)[0]
    rest = skin_points(points, weights, rest_transforms)[0]
    assert torch.equal(posed[outside], rest[outside])
    moved = (posed[inside] - points[inside]).norm(dim=-1)
    # points rigidly attached to the rotated subtree keep their distance to the joint
    distance_before = (points[inside] - joints[joint]).norm(dim=-1)
    distance_after = (posed[inside] - joints[joint]).norm(dim=-1)
    torch.testing.assert_close(distance_after, distance_before)
    assert (moved > 1e-3).float().mean() > 0.9

    means, posed_quats = skin_gaussians(points, quats, weights, posed_transforms[0])
    rest_means, rest_quats = skin_gaussians(points, quats, weights, rest_transforms[0])
    assert torch.equal(means[outside], rest_means[outside])
    assert torch.equal(posed_quats[outside], rest_quats[outside])


def test_skin_gaussians_matches_svd_polar_reference() -> None:
    generator = torch.Generator().manual_seed(5)
    joints = _rest_joints(generator)
    pose = 0.5 * torch.randn(1, NUM_JOINTS, 3, generator=generator, dtype=torch.float64)
    transforms = forward_kinematics(pose, joints, torch.randn(1, 3, generator=generator, dtype=torch.float64))[0]
    means = torch.randn(300, 3, generator=generator, dtype=torch.float64)
    quats = torch.randn(300, 4, generator=generator, dtype=torch.float64)
    weights = _sparse_weights(300, generator)

    posed_means, posed_quats = skin_gaussians(means, quats, weights, transforms)

    blended = torch.einsum("nj,jab->nab", weights, transforms)
    torch.testing.assert_close(posed_means, (blended[:, :3, :3] @ means[..., None])[..., 0] + blended[:, :3, 3])
    u, _, vh = torch.linalg.svd(blended[:, :3, :3])
    polar = u @ vh
    assert (torch.linalg.det(polar) > 0).all()
    torch.testing.assert_close(quaternion_to_matrix(posed_quats), polar @ quaternion_to_matrix(quats))
    torch.testing.assert_close(posed_quats.norm(dim=-1), quats.norm(dim=-1))
    torch.testing.assert_close(skin_points(means, weights, transforms[None])[0], posed_means)


@pytest.mark.parametrize("scale", [0.0, 0.8])
def test_skinning_gradcheck_wrt_pose_translation_and_gaussians(scale: float) -> None:
    generator = torch.Generator().manual_seed(6)
    joints = _rest_joints(generator)
    pose = (scale * torch.randn(2, NUM_JOINTS, 3, generator=generator, dtype=torch.float64)).requires_grad_()
    transl = torch.randn(2, 3, generator=generator, dtype=torch.float64).requires_grad_()
    points = torch.randn(5, 3, generator=generator, dtype=torch.float64).requires_grad_()
    quats = torch.randn(5, 4, generator=generator, dtype=torch.float64).requires_grad_()
    weights = _sparse_weights(5, generator, per_point=4)

    def posed_points(pose: torch.Tensor, transl: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        return skin_points(points, weights, forward_kinematics(pose, joints, transl))

    def posed_gaussians(
        pose: torch.Tensor, transl: torch.Tensor, means: torch.Tensor, quats: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        return skin_gaussians(means, quats, weights, forward_kinematics(pose, joints, transl)[0])

    assert torch.autograd.gradcheck(posed_points, (pose, transl, points))
    first_pose, first_transl = pose[:1].detach().requires_grad_(), transl[:1].detach().requires_grad_()
    assert torch.autograd.gradcheck(posed_gaussians, (first_pose, first_transl, points, quats))


def test_skin_points_matches_per_point_blend_over_batch_dimensions() -> None:
    generator = torch.Generator().manual_seed(8)
    joints = _rest_joints(generator)
    pose = 0.6 * torch.randn(6, NUM_JOINTS, 3, generator=generator, dtype=torch.float64)
    transforms = forward_kinematics(pose, joints, torch.randn(6, 3, generator=generator, dtype=torch.float64)).reshape(2, 3, NUM_JOINTS, 4, 4)
    points = torch.randn(40, 3, generator=generator, dtype=torch.float64)
    weights = _sparse_weights(40, generator).requires_grad_()

    posed = skin_points(points, weights, transforms)

    assert posed.shape == (2, 3, 40, 3)
    for batch in range(2):
        for frame in range(3):
            blended = torch.einsum("nj,jab->nab", weights, transforms[batch, frame])
            torch.testing.assert_close(posed[batch, frame], (blended[:, :3, :3] @ points[..., None])[..., 0] + blended[:, :3, 3])
    assert torch.autograd.gradcheck(lambda w: skin_points(points, w, transforms[0, :2]), (weights,))


def test_quaternion_round_trip_in_every_branch() -> None:
    generator = torch.Generator().manual_seed(7)
    quats = torch.nn.functional.normalize(torch.randn(200, 4, generator=generator, dtype=torch.float64), dim=-1)
    # near-pi rotations about each axis select the x, y and z branches; the identity the w branch
    special = torch.tensor(
        [[1, 0, 0, 0], [1e-3, 1, 0, 0], [1e-3, 0, 1, 0], [1e-3, 0, 0, 1], [0, 1, 1, 0], [0, 0, -1, 1]],
        dtype=torch.float64,
    )
    quats = torch.cat([quats, torch.nn.functional.normalize(special, dim=-1)])
    recovered = matrix_to_quaternion(quaternion_to_matrix(quats))
    signs = torch.where(quats[:, :1] < 0, -1.0, 1.0).to(torch.float64)
    torch.testing.assert_close(recovered, quats * signs)
    rotations = torch.linalg.matrix_exp(_skew(2.5 * torch.randn(100, 3, generator=generator, dtype=torch.float64)))
    torch.testing.assert_close(quaternion_to_matrix(matrix_to_quaternion(rotations)), rotations)


def _concentrated_weights(n: int, generator: torch.Generator) -> torch.Tensor:
    """Softmax weights with most of each point's mass on 1 to 3 random joints."""
    logits = torch.zeros(n, NUM_JOINTS, dtype=torch.float64)
    for count in (1, 2, 3):
        rows = torch.arange(n)[torch.arange(n) % 3 == count - 1]
        joints = torch.randint(0, NUM_JOINTS, (rows.shape[0], count), generator=generator)
        boost = 6.0 + 4.0 * torch.rand(rows.shape[0], count, generator=generator, dtype=torch.float64)
        logits[rows[:, None], joints] = boost
    return torch.softmax(logits, dim=-1)


def _skinning_case(n: int, dtype: torch.dtype, seed: int) -> list[torch.Tensor]:
    """means (n, 3), quats (n, 4), concentrated weights (n, 24), FK transforms (24, 4, 4) of a random pose."""
    generator = torch.Generator().manual_seed(seed)
    joints = _rest_joints(generator)
    pose = 0.8 * torch.randn(1, NUM_JOINTS, 3, generator=generator, dtype=torch.float64)
    transforms = forward_kinematics(pose, joints, torch.randn(1, 3, generator=generator, dtype=torch.float64))[0]
    means = torch.randn(n, 3, generator=generator, dtype=torch.float64)
    quats = torch.randn(n, 4, generator=generator, dtype=torch.float64)
    return [tensor.to(dtype) for tensor in (means, quats, _concentrated_weights(n, generator), transforms)]


def _skin_with_gradients(
    inputs: list[torch.Tensor], backend: str, upstream: tuple[torch.Tensor, torch.Tensor]
) -> list[torch.Tensor]:
    """posed means, posed quats, then the gradients of <upstream, outputs> w.r.t. means, quats, weights, transforms."""
    leaves = [tensor.clone().requires_grad_() for tensor in inputs]
    posed_means, posed_quats = skin_gaussians(*leaves, backend=backend)
    grads = torch.autograd.grad([posed_means, posed_quats], leaves, list(upstream))
    return [posed_means.detach(), posed_quats.detach(), *grads]


def _assert_close_relative(actual: torch.Tensor, expected: torch.Tensor, tolerance: float) -> None:
    """Every entry within `tolerance` times the largest magnitude in `expected`."""
    torch.testing.assert_close(actual, expected, rtol=tolerance, atol=tolerance * expected.abs().max().item())


def _assert_backends_agree(inputs: list[torch.Tensor], tolerance: float, seed: int) -> None:
    generator = torch.Generator().manual_seed(seed)
    n, dtype = inputs[0].shape[0], inputs[0].dtype
    upstream = (torch.randn(n, 3, generator=generator).to(dtype), torch.randn(n, 4, generator=generator).to(dtype))
    numba_results = _skin_with_gradients(inputs, "numba", upstream)
    torch_results = _skin_with_gradients(inputs, "torch", upstream)
    for actual, expected in zip(torch_results, numba_results):
        _assert_close_relative(actual, expected, tolerance)


@pytest.mark.parametrize(("dtype", "tolerance"), [(torch.float32, 1e-5), (torch.float64, 1e-10)])
@pytest.mark.parametrize("seed", [10, 11, 12])
def test_torch_skinning_matches_numba_forward_and_backward(dtype: torch.dtype, tolerance: float, seed: int) -> None:
    _assert_backends_agree(_skinning_case(3000, dtype, seed), tolerance, seed)


def test_torch_skinning_without_gradients_gives_the_same_values() -> None:
    inputs = _skinning_case(500, torch.float32, 13)
    with torch.no_grad():
        plain = skin_gaussians(*inputs, backend="torch")
    tracked = skin_gaussians(*[tensor.clone().requires_grad_() for tensor in inputs], backend="torch")
    for value, with_graph in zip(plain, tracked):
        assert torch.equal(value, with_graph.detach())


def test_auto_backend_is_numba_on_the_cpu_and_unknown_backends_are_refused() -> None:
    inputs = _skinning_case(200, torch.float32, 14)
    for auto, numba_result in zip(skin_gaussians(*inputs), skin_gaussians(*inputs, backend="numba")):
        assert torch.equal(auto, numba_result)
    with pytest.raises(ValueError, match="cuda"):
        skin_gaussians(*inputs, backend="cuda")


def test_torch_skinning_gradcheck() -> None:
    means, quats, weights, transforms = _skinning_case(6, torch.float64, 15)

    def skin(
        means: torch.Tensor, quats: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        return skin_gaussians(means, quats, weights, transforms, backend="torch")

    inputs = tuple(tensor.requires_grad_() for tensor in (means, quats, weights, transforms))
    # fast mode (a random projection of the Jacobian, checked against finite differences) keeps the
    # 570 inputs to a second; the pose gradchecks below use the full Jacobian
    assert torch.autograd.gradcheck(skin, inputs, fast_mode=True)


@pytest.mark.parametrize("scale", [0.0, 0.8])
def test_torch_skinning_gradcheck_wrt_pose(scale: float) -> None:
    generator = torch.Generator().manual_seed(16)
    joints = _rest_joints(generator)
    pose = (scale * torch.randn(1, NUM_JOINTS, 3, generator=generator, dtype=torch.float64)).requires_grad_()
    transl = torch.randn(1, 3, generator=generator, dtype=torch.float64).requires_grad_()
    means = torch.randn(5, 3, generator=generator, dtype=torch.float64)
    quats = torch.randn(5, 4, generator=generator, dtype=torch.float64)
    weights = _sparse_weights(5, generator, per_point=4)

    def skin(pose: torch.Tensor, transl: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return skin_gaussians(means, quats, weights, forward_kinematics(pose, joints, transl)[0], backend="torch")

    assert torch.autograd.gradcheck(skin, (pose, transl))


def _edge_transforms() -> torch.Tensor:
    """(24, 4, 4): joint 0 the identity, 1-3 half turns about x, y, z, 4-6 turns by pi - 1e-3 about x, y, z,
    7 the half turn about (1, 1, 0) (equal t1 and t2: a tie between quaternion branches), the rest random."""
    generator = torch.Generator().manual_seed(17)
    axis_angles = 0.5 * torch.randn(NUM_JOINTS, 3, generator=generator, dtype=torch.float64)
    axis_angles[0] = 0.0
    axis_angles[4:7] = (torch.pi - 1e-3) * torch.eye(3, dtype=torch.float64)
    transforms = torch.eye(4, dtype=torch.float64).repeat(NUM_JOINTS, 1, 1)
    transforms[:, :3, :3] = axis_angle_to_matrix(axis_angles)
    eye = torch.eye(3, dtype=torch.float64)
    transforms[1:4, :3, :3] = 2 * torch.diag_embed(eye) - eye  # diag(1, -1, -1) and its permutations
    transforms[7, :3, :3] = torch.tensor([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]], dtype=torch.float64)
    transforms[:, :3, 3] = torch.randn(NUM_JOINTS, 3, generator=generator, dtype=torch.float64)
    return transforms


def _edge_weights() -> torch.Tensor:
    """Rows: each of joints 0-7 alone; near-opposite pairs (the identity and a half turn, nearly rank 1);
    three half turns (a blend with negative determinant); two turns by pi - 1e-3 about different axes."""
    rows = [[(joint, 1.0)] for joint in range(8)]
    rows += [[(0, 0.5 + 1e-6), (1, 0.5 - 1e-6)], [(0, 0.5 - 1e-4), (2, 0.5 + 1e-4)], [(0, 0.6), (3, 0.4)]]
    rows += [[(1, 0.4), (2, 0.35), (3, 0.25)], [(4, 0.5), (5, 0.5)], [(5, 0.3), (6, 0.7)]]
    weights = torch.zeros(len(rows), NUM_JOINTS, dtype=torch.float64)
    for row, entries in enumerate(rows):
        for joint, weight in entries:
            weights[row, joint] = weight
    return weights


def test_torch_skinning_matches_numba_on_degenerate_blends_and_every_quaternion_branch() -> None:
    weights = _edge_weights()
    transforms = _edge_transforms()
    generator = torch.Generator().manual_seed(18)
    means = torch.randn(weights.shape[0], 3, generator=generator, dtype=torch.float64)
    quats = torch.randn(weights.shape[0], 4, generator=generator, dtype=torch.float64)
    _assert_backends_agree([means, quats, weights, transforms], 1e-10, seed=19)
    # Nearly rank-1 blends (two singular values ~1e-4) amplify float32 rounding in the torch path's float32
    # arithmetic (the numba kernel iterates in float64) by ~1e4, so float32 is compared on the others only.
    blended = torch.einsum("nj,jab->nab", weights, transforms)
    linear = blended[:, :3, :3]
    well_conditioned = torch.linalg.svdvals(linear)[:, 1:].sum(-1) > 0.1
    assert well_conditioned.sum() == weights.shape[0] - 3
    kept = [tensor[well_conditioned].float() for tensor in (means, quats, weights)]
    _assert_backends_agree([*kept, transforms.float()], 1e-5, seed=19)

    posed_means, posed_quats = skin_gaussians(means, quats, weights, transforms, backend="torch")
    torch.testing.assert_close(posed_means, (linear @ means[..., None])[..., 0] + blended[:, :3, 3])
    # reference rotation: the SVD polar factor U V^T, negated where det M < 0 as the kernel documents
    u, _, vh = torch.linalg.svd(linear)
    reference = (u @ vh) * torch.sign(torch.linalg.det(linear))[:, None, None]
    assert (torch.linalg.det(reference) > 0).all()
    torch.testing.assert_close(quaternion_to_matrix(posed_quats), reference @ quaternion_to_matrix(quats))
    torch.testing.assert_close(posed_quats.norm(dim=-1), quats.norm(dim=-1))
    # single joints: the rotation quaternion r = posed * conj(q) / |q|^2 has w >= 0 and is the joint's own
    single = posed_quats[:8]
    conj = quats[:8] * torch.tensor([1.0, -1, -1, -1], dtype=torch.float64)
    w, x, y, z = single.unbind(-1)
    cw, cx, cy, cz = conj.unbind(-1)
    rotation_quats = torch.stack(
        [w * cw - x * cx - y * cy - z * cz, w * cx + x * cw + y * cz - z * cy,
         w * cy - x * cz + y * cw + z * cx, w * cz + x * cy - y * cx + z * cw],
        dim=-1,
    ) / quats[:8].norm(dim=-1, keepdim=True) ** 2  # fmt: skip
    torch.testing.assert_close(rotation_quats, matrix_to_quaternion(transforms[:8, :3, :3]))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize(("dtype", "tolerance"), [(torch.float32, 1e-5), (torch.float64, 1e-10)])
def test_torch_skinning_on_cuda_matches_numba_forward_and_backward(dtype: torch.dtype, tolerance: float) -> None:
    inputs = _skinning_case(3000, dtype, 10)  # the case the CPU test above checks the torch path on
    generator = torch.Generator().manual_seed(10)
    upstream = (torch.randn(3000, 3, generator=generator).to(dtype), torch.randn(3000, 4, generator=generator).to(dtype))
    expected = _skin_with_gradients(inputs, "numba", upstream)
    actual = _skin_with_gradients([t.cuda() for t in inputs], "auto", tuple(u.cuda() for u in upstream))
    for value, reference in zip(actual, expected):
        assert value.is_cuda
        _assert_close_relative(value.cpu(), reference, tolerance)


def test_joint_displacements_sum_each_chain() -> None:
    from avatarperfect_cli.body.base import SMPL_PARENTS, joint_displacements

    offsets = torch.randn(24, 3, dtype=torch.float64)
    expected = torch.zeros(24, 3, dtype=torch.float64)
    for joint in range(24):
        ancestor = joint
        while ancestor >= 0:
            expected[joint] += offsets[ancestor]
            ancestor = SMPL_PARENTS[ancestor]
    torch.testing.assert_close(joint_displacements(offsets), expected)


def test_bone_offsets_move_joints_and_the_vertices_they_drive() -> None:
    from avatarperfect_cli.body.base import BodyTemplate

    weights = torch.zeros(3, 24)
    weights[0, 0], weights[1, 4], weights[2, 4], weights[2, 1] = 1.0, 1.0, 0.5, 0.5  # root, left knee, a blend
    template = BodyTemplate(torch.zeros(3, 3), torch.zeros(1, 3, dtype=torch.long), weights, torch.zeros(24, 3))
    offsets = torch.zeros(24, 3)
    offsets[4] = torch.tensor([0.0, -0.02, 0.0])  # a 2 cm longer thigh: the knee and everything below move
    moved = template.with_bone_offsets(offsets)
    torch.testing.assert_close(moved.rest_joints[[4, 7, 10]], offsets[4].expand(3, 3))
    torch.testing.assert_close(moved.rest_joints[[0, 1, 2, 5]], torch.zeros(4, 3))
    torch.testing.assert_close(moved.vertices, torch.tensor([[0.0, 0.0, 0.0], [0.0, -0.02, 0.0], [0.0, -0.01, 0.0]]))


def test_skin_points_blends_each_joints_transformed_point_for_any_batch_shape() -> None:
    """Against the definition, point by point: sum over joints of w_nj (T_j [p_n; 1]), for a (2, 3) batch."""
    generator = torch.Generator().manual_seed(7)
    points = torch.randn(6, 3, generator=generator, dtype=torch.float64)
    weights = _sparse_weights(6, generator, per_point=4)
    transforms = torch.randn(2, 3, NUM_JOINTS, 4, 4, generator=generator, dtype=torch.float64)
    posed = skin_points(points, weights, transforms)
    assert posed.shape == (2, 3, 6, 3)
    for b, c, n in ((b, c, n) for b in range(2) for c in range(3) for n in range(6)):
        homogeneous = torch.cat([points[n], torch.ones(1, dtype=torch.float64)])
        expected = sum(weights[n, j] * (transforms[b, c, j] @ homogeneous)[:3] for j in range(NUM_JOINTS))
        torch.testing.assert_close(posed[b, c, n], expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(skin_points(points, weights, transforms[1, 2]), posed[1, 2], rtol=1e-12, atol=1e-12)


def _dense_skin(points: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """The definition as dense tensors: (..., N, 3) = sum_j w_nj (A_j [p_n; 1])[:3]."""
    homogeneous = torch.cat([points, torch.ones_like(points[:, :1])], dim=1)
    per_joint = torch.einsum("...jab,nb->...nja", transforms[..., :3, :], homogeneous)
    return (weights[..., None] * per_joint).sum(dim=-2)


def test_skin_points_sparse_kernels_match_the_dense_definition_and_its_gradients() -> None:
    """Few nonzero weights per point (the kernels' path), signed and unsorted, and a point with none: the
    posed points and the gradients for points and transforms against autograd through the dense definition."""
    generator = torch.Generator().manual_seed(11)
    points = torch.randn(30, 3, generator=generator, dtype=torch.float64)
    weights = _sparse_weights(30, generator, per_point=5)
    weights[3] *= -0.5  # signed (refine's weight changes are)
    weights[7] = 0.0
    transforms = torch.randn(2, 4, NUM_JOINTS, 4, 4, generator=generator, dtype=torch.float64)
    grad = torch.randn(2, 4, 30, 3, generator=generator, dtype=torch.float64)
    results = []
    for skin in (skin_points, _dense_skin):
        leaves = points.clone().requires_grad_(), transforms.clone().requires_grad_()
        posed = skin(leaves[0], weights, leaves[1])
        posed.backward(grad)
        results.append((posed.detach(), leaves[0].grad, leaves[1].grad))
    for got, expected in zip(*results):
        torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-12)
    assert results[0][0][:, :, 7].abs().max() == 0.0
    assert torch.autograd.gradcheck(lambda p, t: skin_points(p, weights[:8], t), (points[:8].clone().requires_grad_(), transforms[0, :2].clone().requires_grad_()))


def test_skin_points_with_many_nonzero_weights_per_point_still_blends_every_joint() -> None:
    """More nonzero weights per point than the kernels take (a dense change of weights) and float32: the
    matrix-product path, against the dense definition."""
    generator = torch.Generator().manual_seed(12)
    points = torch.randn(20, 3, generator=generator)
    weights = torch.randn(20, NUM_JOINTS, generator=generator)
    transforms = torch.randn(3, NUM_JOINTS, 4, 4, generator=generator)
    torch.testing.assert_close(skin_points(points, weights, transforms), _dense_skin(points, weights, transforms), rtol=1e-4, atol=1e-4)
