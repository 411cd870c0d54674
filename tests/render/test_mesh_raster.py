"""The ground-truth mesh rasterizer against a dense ray-casting reference and analytic cases."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatarperfect_cli.render.camera import Camera, look_at
from avatarperfect_cli.render.mesh_raster import mesh_coverage, render_mesh, vertex_normals

TEXTURE_SIZE = 64


def _camera(width: int = 16, height: int = 16, eye=(0.3, -0.2, -3.0)) -> Camera:
    K = [[18.0, 0.4, width / 2 + 0.3], [0.0, 17.0, height / 2 - 0.2], [0.0, 0.0, 1.0]]  # with skew
    K = torch.tensor(K, dtype=torch.float64)
    view = look_at(torch.tensor(eye, dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                   torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))  # fmt: skip
    return Camera(K, view, width, height)


def _ramp_texture() -> np.ndarray:
    """Texture whose bilinear lookup returns (u, v, 0.5) exactly for u, v in [0.5, 63.5] / 64."""
    centres = (np.arange(TEXTURE_SIZE) + 0.5) / TEXTURE_SIZE
    texture = np.empty((TEXTURE_SIZE, TEXTURE_SIZE, 3), np.float32)
    texture[:, :, 0] = centres[None, :]
    texture[:, :, 1] = centres[::-1, None]  # row 0 holds v = 1
    texture[:, :, 2] = 0.5
    return texture


def _two_triangles() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two tilted triangles that cross in depth, with UVs inside the ramp's exact range."""
    vertices = np.array(
        [[-0.9, -0.8, 0.3], [0.8, -0.7, -0.2], [0.1, 0.9, 0.1],
         [-0.7, 0.6, -0.3], [0.9, 0.5, 0.35], [-0.2, -0.9, -0.1]], dtype=np.float64,
    )  # fmt: skip
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    uvs = np.array([[0.1, 0.1], [0.9, 0.2], [0.5, 0.9], [0.2, 0.8], [0.85, 0.6], [0.3, 0.15]])
    return vertices, faces, uvs


def _ray_cast(vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray, camera: Camera):
    """Dense reference: one ray per pixel centre against every triangle (Moller-Trumbore, float64).

    Returns the nearest face per pixel (-1: none) and the UV at the hit point.
    """
    view = camera.world_to_camera.numpy()
    points = vertices @ view[:3, :3].T + view[:3, 3]
    cols, rows = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    pixels = np.stack([cols, rows, np.ones_like(cols)], axis=-1)
    rays = pixels @ np.linalg.inv(camera.K.numpy()).T  # (H, W, 3), z = 1
    best_t = np.full(cols.shape, np.inf)
    face_id = np.full(cols.shape, -1)
    hit_uv = np.zeros(cols.shape + (2,))
    for f, (a, b, c) in enumerate(faces):
        e1, e2 = points[b] - points[a], points[c] - points[a]
        p = np.cross(rays, e2)
        det = p @ e1
        s = -points[a]
        u = np.einsum("hwc,c->hw", p, s) / det
        q = np.cross(s, e1)
        v = (rays @ q) / det
        t = (q @ e2) / det
        hit = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t < best_t)
        best_t[hit] = t[hit]
        face_id[hit] = f
        uv = (1 - u - v)[..., None] * uvs[a] + u[..., None] * uvs[b] + v[..., None] * uvs[c]
        hit_uv[hit] = uv[hit]
    return face_id, hit_uv


def test_coverage_depth_order_and_uv_match_ray_casting() -> None:
    vertices, faces, uvs = _two_triangles()
    camera = _camera()
    result = render_mesh(vertices, faces, uvs, faces, _ramp_texture(), camera, face_labels=np.arange(2), supersample=1)
    face_id, hit_uv = _ray_cast(vertices, faces, uvs, camera)

    assert (face_id == 0).sum() > 10 and (face_id == 1).sum() > 10  # both triangles win somewhere
    np.testing.assert_array_equal(result.labels, face_id)
    np.testing.assert_array_equal(result.coverage, (face_id >= 0).astype(np.float32))
    covered = face_id >= 0
    np.testing.assert_allclose(result.rgb[covered][:, :2], hit_uv[covered], atol=2e-6)
    np.testing.assert_allclose(result.rgb[~covered], 1.0)


def test_supersampling_is_the_area_average_of_a_finer_render() -> None:
    vertices, faces, uvs = _two_triangles()
    camera = _camera()
    background = (0.2, 0.3, 0.4)
    coarse = render_mesh(vertices, faces, uvs, faces, _ramp_texture(), camera, supersample=2, background=background)
    fine = render_mesh(
        vertices, faces, uvs, faces, _ramp_texture(), camera.scaled(2), supersample=1, background=background
    )
    np.testing.assert_allclose(coarse.rgb, fine.rgb.reshape(16, 2, 16, 2, 3).mean(axis=(1, 3)), atol=1e-6)
    np.testing.assert_allclose(coarse.coverage, fine.coverage.reshape(16, 2, 16, 2).mean(axis=(1, 3)))
    assert ((coarse.coverage > 0) & (coarse.coverage < 1)).any()  # there are edge pixels



def test_mesh_coverage_is_the_share_of_ray_cast_subsamples_that_hit() -> None:
    """Silhouettes: each pixel's coverage is the share of its 3 x 3 subsample rays (the reference ray
    caster at three times the resolution) that hit a triangle."""
    vertices, faces, uvs = _two_triangles()
    camera = _camera()
    face_id, _ = _ray_cast(vertices, faces, uvs, camera.scaled(3))
    expected = (face_id >= 0).reshape(16, 3, 16, 3).mean(axis=(1, 3))
    coverage = mesh_coverage(vertices, faces, camera, supersample=3)
    assert coverage.dtype == np.float32 and coverage.shape == (16, 16)
    np.testing.assert_allclose(coverage, expected, atol=1e-6)
    assert ((coverage > 0) & (coverage < 1)).sum() > 10 and (coverage == 1).sum() > 10

def _tilted_plane(size: int = 1):
    """A quad on the plane through the origin with normal n, spanned by unit vectors e_u, e_v."""
    normal = np.array([0.35, -0.25, -1.0])
    normal /= np.linalg.norm(normal)
    e_u = np.cross([0.0, 1.0, 0.0], normal)
    e_u /= np.linalg.norm(e_u)
    e_v = np.cross(normal, e_u)
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64) * 1.2
    vertices = corners[:, :1] * e_u + corners[:, 1:] * e_v
    uvs = 0.1 + 0.8 * (corners + 1.2) / 2.4
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    return vertices, faces, uvs, normal, e_u, e_v


def test_textured_plane_matches_the_analytic_projection() -> None:
    vertices, faces, uvs, normal, e_u, e_v = _tilted_plane()
    camera = _camera(24, 20)
    result = render_mesh(vertices, faces, uvs, faces, _ramp_texture(), camera, supersample=1)

    view = camera.world_to_camera.numpy()
    eye = camera.center.numpy()
    cols, rows = np.meshgrid(np.arange(24) + 0.5, np.arange(20) + 0.5)
    rays_cam = np.stack([cols, rows, np.ones_like(cols)], -1) @ np.linalg.inv(camera.K.numpy()).T
    rays = rays_cam @ view[:3, :3]  # world directions
    t = -(eye @ normal) / (rays @ normal)
    hits = eye + t[..., None] * rays
    # The quad maps plane coordinates in [-1.2, 1.2] linearly onto UV [0.1, 0.9].
    expected_u = 0.1 + 0.8 * (hits @ e_u + 1.2) / 2.4
    expected_v = 0.1 + 0.8 * (hits @ e_v + 1.2) / 2.4
    inside = result.coverage == 1.0
    assert inside.sum() > 100
    np.testing.assert_allclose(result.rgb[inside][:, 0], expected_u[inside], atol=2e-6)
    np.testing.assert_allclose(result.rgb[inside][:, 1], expected_v[inside], atol=2e-6)


def test_headlight_shading_follows_the_cosine_to_the_view_ray() -> None:
    vertices, faces, uvs, normal, _, _ = _tilted_plane()
    camera = _camera(24, 20)
    white = np.ones((4, 4, 3), np.float32)
    normals = np.repeat(normal[None], 4, axis=0)
    result = render_mesh(vertices, faces, uvs, faces, white, camera, normals=normals, ambient=0.4, supersample=1)

    cols, rows = np.meshgrid(np.arange(24) + 0.5, np.arange(20) + 0.5)
    rays_cam = np.stack([cols, rows, np.ones_like(cols)], -1) @ np.linalg.inv(camera.K.numpy()).T
    rays = rays_cam @ camera.world_to_camera.numpy()[:3, :3]
    cosine = np.abs(rays @ normal) / np.linalg.norm(rays, axis=-1)
    inside = result.coverage == 1.0
    np.testing.assert_allclose(result.rgb[inside][:, 0], 0.4 + 0.6 * cosine[inside], atol=1e-6)


def test_back_faces_are_culled_only_on_request() -> None:
    vertices, faces, uvs = _two_triangles()
    camera = _camera()
    face_id, _ = _ray_cast(vertices, faces, uvs, camera)
    # Orient triangle 0 towards the camera (its normal points at the eye) and triangle 1 away from it.
    corners = vertices[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    towards = np.einsum("fc,fc->f", normals, camera.center.numpy() - corners[:, 0]) > 0
    front = np.where(towards[:, None], faces, faces[:, ::-1])
    mixed = np.stack([front[0], front[1][::-1]])
    both = render_mesh(vertices, mixed, uvs, mixed, _ramp_texture(), camera, face_labels=np.arange(2), supersample=1)
    culled = render_mesh(vertices, mixed, uvs, mixed, _ramp_texture(), camera, face_labels=np.arange(2),
                         supersample=1, cull_back_faces=True)  # fmt: skip
    np.testing.assert_array_equal(both.labels, face_id)
    only_front, _ = _ray_cast(vertices, faces[:1], uvs, camera)
    np.testing.assert_array_equal(culled.labels, only_front)


def test_majority_labels_ignore_pixels_mostly_background() -> None:
    vertices, faces, uvs, _, _, _ = _tilted_plane()
    camera = _camera(24, 20)
    result = render_mesh(vertices, faces, uvs, faces, _ramp_texture(), camera, face_labels=np.array([7, 9]))
    np.testing.assert_array_equal(result.labels >= 0, result.coverage >= 0.5)
    assert set(np.unique(result.labels)) == {-1, 7, 9}


@pytest.mark.parametrize("seed", [0, 1])
def test_vertex_normals_of_a_sphere_point_outwards(seed: int) -> None:
    rng = np.random.default_rng(seed)
    # A regular octahedron: by symmetry each vertex normal is the vertex direction.
    base = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64)
    faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    rotation *= np.sign(np.linalg.det(rotation))  # a proper rotation keeps the faces' orientation
    normals = vertex_normals(base @ rotation.T, faces)
    np.testing.assert_allclose(normals, base @ rotation.T, atol=1e-12)
