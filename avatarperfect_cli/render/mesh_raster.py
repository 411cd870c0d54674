"""A small CPU mesh rasterizer: ground-truth images of the synthetic subject, and body silhouettes.

It is independent of the Gaussian renderer on purpose: z-buffered triangles, perspective-correct
barycentrics, bilinear UV texture lookup, optional headlight shading, and supersampling
anti-aliasing (render at `supersample`x, then average each block of subsamples).

Conventions: OpenCV pinhole camera (our `Camera`), pixel (row i, column j) samples the image point
(j + 0.5, i + 0.5). Texture row 0 holds v = 1 (the OBJ/OpenGL convention), column 0 holds u = 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numba import njit, prange

from avatarperfect_cli.render.camera import Camera

_BAND_ROWS = 8  # rows of the supersampled image per work item
_NEAR = 1e-3  # metres; triangles with a vertex closer than this to the camera plane are skipped


@dataclass
class MeshRender:
    """A rendered frame.

    rgb:      (H, W, 3) float32 in [0, 1], composited on the background colour
    coverage: (H, W) float32 in [0, 1], the fraction of each pixel's subsamples the mesh covers
    labels:   (H, W) int32 face label seen by most of the pixel's covered subsamples, -1 where
              coverage < 0.5 (background), or None
    """

    rgb: np.ndarray
    coverage: np.ndarray
    labels: np.ndarray | None


def render_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    uvs: np.ndarray,
    face_uvs: np.ndarray,
    texture: np.ndarray,
    camera: Camera,
    *,
    normals: np.ndarray | None = None,
    ambient: float = 1.0,
    face_labels: np.ndarray | None = None,
    supersample: int = 2,
    cull_back_faces: bool = False,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
) -> MeshRender:
    """Render a textured triangle mesh.

    vertices:    (V, 3) world frame, metres
    faces:       (F, 3) vertex indices, counter-clockwise seen from outside
    uvs:         (T, 2) texture coordinates in [0, 1]; face_uvs: (F, 3) indices into `uvs`
    texture:     (Ht, Wt, 3) float32 in [0, 1] or uint8
    normals:     (V, 3) world-frame vertex normals for headlight shading, or None for flat albedo;
                 the shade is ambient + (1 - ambient) * |cos(normal, view ray)|
    face_labels: (F,) integer label per face for the `labels` output, or None
    supersample: subsamples per pixel along each axis
    cull_back_faces: drop faces whose front side faces away from the camera
    """
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    fine = camera.scaled(supersample)
    rotation = camera.world_to_camera[:3, :3].double().numpy()
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    points, screen, keep = _screen_points(vertices, faces, fine)
    K = fine.K.double().numpy()
    if cull_back_faces:
        corners = points[faces]
        face_normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        keep &= np.einsum("fc,fc->f", face_normal, corners[:, 0]) < 0.0
    face_id, bary = rasterize_triangles(screen, faces, fine.width, fine.height, keep)

    shade_normals = np.zeros((0, 3)) if normals is None else np.asarray(normals, np.float64) @ rotation.T
    K_inv = np.linalg.inv(K)
    texels = np.ascontiguousarray(texture, dtype=np.float32)
    if texture.dtype == np.uint8:
        texels /= 255.0
    rgb, coverage = _shade(
        face_id, bary, screen, faces, np.asarray(uvs, np.float64), np.ascontiguousarray(face_uvs, np.int64),
        texels, shade_normals, K_inv, float(ambient), np.asarray(background, np.float32), supersample,
    )  # fmt: skip
    labels = None
    if face_labels is not None:
        labels = _majority_labels(
            face_id, np.ascontiguousarray(face_labels, np.int32), supersample, camera.height, camera.width
        )
    return MeshRender(rgb=rgb, coverage=coverage, labels=labels)


def mesh_coverage(vertices: np.ndarray, faces: np.ndarray, camera: Camera, supersample: int = 2) -> np.ndarray:
    """(H, W) float32 in [0, 1]: the fraction of each pixel's supersample x supersample subsamples the mesh
    covers (its silhouette). vertices: (V, 3) world frame, metres; faces: (F, 3) vertex indices."""
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    fine = camera.scaled(supersample)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    _, screen, keep = _screen_points(vertices, faces, fine)
    face_id, _ = rasterize_triangles(screen, faces, fine.width, fine.height, keep)
    covered = (face_id >= 0).reshape(camera.height, supersample, camera.width, supersample)
    return covered.mean(axis=(1, 3), dtype=np.float32)


def _screen_points(vertices: np.ndarray, faces: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The vertices in the camera frame (V, 3) metres, on the screen (V, 3): pixel x, pixel y and inverse
    depth, and the faces (F,) bool whose every vertex lies in front of the near plane."""
    rotation = camera.world_to_camera[:3, :3].double().numpy()
    translation = camera.world_to_camera[:3, 3].double().numpy()
    points = np.asarray(vertices, dtype=np.float64) @ rotation.T + translation
    K = camera.K.double().numpy()
    depth = points[:, 2]
    safe_depth = np.where(depth > _NEAR, depth, 1.0)
    screen = np.empty((len(points), 3))
    screen[:, 0] = K[0, 0] * points[:, 0] / safe_depth + K[0, 1] * points[:, 1] / safe_depth + K[0, 2]
    screen[:, 1] = K[1, 1] * points[:, 1] / safe_depth + K[1, 2]
    screen[:, 2] = 1.0 / safe_depth
    return points, screen, (depth[faces] > _NEAR).all(axis=1)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) unit vertex normals, the area-weighted mean of the adjacent faces' normals (outward for
    counter-clockwise faces). vertices: (V, 3); faces: (F, 3)."""
    corners = vertices[faces]
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # length 2 * area
    index = np.asarray(faces).reshape(-1)
    repeated = np.repeat(face_normals, 3, axis=0)
    sums = np.stack([np.bincount(index, repeated[:, c], minlength=len(vertices)) for c in range(3)], axis=1)
    return sums / np.maximum(np.linalg.norm(sums, axis=1, keepdims=True), 1e-20)


def rasterize_triangles(
    screen: np.ndarray, faces: np.ndarray, width: int, height: int, keep: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffered coverage of 2D triangles, sampled at pixel centres (j + 0.5, i + 0.5).

    screen: (P, 3) pixel x, pixel y and inverse depth (the larger value wins; equal values keep the
            lower face index); faces: (F, 3) indices into `screen`; keep: (F,) bool, faces to draw
    returns face_id (H, W) int32 (-1 where empty) and screen-space barycentrics (H, W, 3) float64
    """
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    screen = np.ascontiguousarray(screen, dtype=np.float64)
    keep = np.ones(len(faces), dtype=bool) if keep is None else keep
    band_start, band_faces = _bin_faces(screen, faces, keep, width, height)
    n_workers = min(numba.get_num_threads(), len(band_start) - 1)
    return _rasterize(screen, faces, band_start, band_faces, width, height, n_workers)


def _bin_faces(
    screen: np.ndarray, faces: np.ndarray, keep: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """Faces overlapping each band of rows, as CSR: band b holds band_faces[band_start[b]:band_start[b+1]].

    Faces are listed in increasing index within a band, so ties in the z-buffer resolve the same way
    however the bands are spread over threads.
    """
    corner_y = screen[faces, 1]
    corner_x = screen[faces, 0]
    # Pixel row i is covered only if its centre i + 0.5 lies in [min y, max y].
    row_lo = np.ceil(corner_y.min(axis=1) - 0.5)
    row_hi = np.floor(corner_y.max(axis=1) - 0.5)
    col_lo = np.ceil(corner_x.min(axis=1) - 0.5)
    col_hi = np.floor(corner_x.max(axis=1) - 0.5)
    keep = keep & (row_hi >= 0) & (row_lo <= height - 1) & (col_hi >= 0) & (col_lo <= width - 1) & (row_lo <= row_hi)
    face_index = np.nonzero(keep)[0]
    n_bands = -(-height // _BAND_ROWS)
    first = np.clip(row_lo[face_index], 0, height - 1).astype(np.int64) // _BAND_ROWS
    last = np.clip(row_hi[face_index], 0, height - 1).astype(np.int64) // _BAND_ROWS
    counts = last - first + 1
    owner = np.repeat(face_index, counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    band = np.repeat(first, counts) + offsets
    order = np.lexsort((owner, band))
    band_start = np.zeros(n_bands + 1, dtype=np.int64)
    np.cumsum(np.bincount(band, minlength=n_bands), out=band_start[1:])
    return band_start, owner[order].astype(np.int64)


@njit(cache=True, parallel=True)
def _rasterize(
    screen: np.ndarray,
    faces: np.ndarray,
    band_start: np.ndarray,
    band_faces: np.ndarray,
    width: int,
    height: int,
    n_workers: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffer pass. Returns face_id (H, W) int32 (-1: empty) and screen-space barycentrics (H, W, 3).

    screen: (V, 3) pixel x, pixel y, 1/depth. Bands are dealt round-robin to `n_workers` threads.
    """
    face_id = np.full((height, width), -1, dtype=np.int32)
    bary = np.zeros((height, width, 3), dtype=np.float64)
    inv_depth = np.zeros((height, width), dtype=np.float64)
    n_bands = band_start.shape[0] - 1
    for worker in prange(n_workers):
        for band in range(worker, n_bands, n_workers):
            band_lo = band * _BAND_ROWS
            band_hi = min(band_lo + _BAND_ROWS, height) - 1
            for k in range(band_start[band], band_start[band + 1]):
                f = band_faces[k]
                a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
                ax, ay, az = screen[a, 0], screen[a, 1], screen[a, 2]
                bx, by, bz = screen[b, 0], screen[b, 1], screen[b, 2]
                cx, cy, cz = screen[c, 0], screen[c, 1], screen[c, 2]
                area = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay)
                if area == 0.0:
                    continue
                inv_area = 1.0 / area
                row_lo = max(int(np.ceil(min(ay, by, cy) - 0.5)), band_lo)
                row_hi = min(int(np.floor(max(ay, by, cy) - 0.5)), band_hi)
                col_lo = max(int(np.ceil(min(ax, bx, cx) - 0.5)), 0)
                col_hi = min(int(np.floor(max(ax, bx, cx) - 0.5)), width - 1)
                for i in range(row_lo, row_hi + 1):
                    py = i + 0.5
                    for j in range(col_lo, col_hi + 1):
                        px = j + 0.5
                        wa = ((bx - px) * (cy - py) - (cx - px) * (by - py)) * inv_area
                        wb = ((cx - px) * (ay - py) - (ax - px) * (cy - py)) * inv_area
                        wc = 1.0 - wa - wb
                        if wa < 0.0 or wb < 0.0 or wc < 0.0:
                            continue
                        z = wa * az + wb * bz + wc * cz
                        if z > inv_depth[i, j]:
                            inv_depth[i, j] = z
                            face_id[i, j] = f
                            bary[i, j, 0] = wa
                            bary[i, j, 1] = wb
                            bary[i, j, 2] = wc
    return face_id, bary


@njit(cache=True, parallel=True)
def _shade(
    face_id: np.ndarray,
    bary: np.ndarray,
    screen: np.ndarray,
    faces: np.ndarray,
    uvs: np.ndarray,
    face_uvs: np.ndarray,
    texture: np.ndarray,
    normals: np.ndarray,
    K_inv: np.ndarray,
    ambient: float,
    background: np.ndarray,
    s: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Deferred shading (perspective-correct UV, bilinear texel, optional headlight) of every subsample,
    averaged over each s x s block. Returns rgb (H, W, 3) float32 and coverage (H, W) float32."""
    height, width = face_id.shape[0] // s, face_id.shape[1] // s
    tex_h, tex_w = texture.shape[0], texture.shape[1]
    use_normals = normals.shape[0] > 0
    inv_count = 1.0 / (s * s)
    rgb = np.empty((height, width, 3), dtype=np.float32)
    coverage = np.empty((height, width), dtype=np.float32)
    for pi in prange(height):
        colour = np.empty(3)
        for pj in range(width):
            colour[:] = 0.0
            covered = 0
            for k in range(s * s):
                i = pi * s + k // s
                j = pj * s + k % s
                f = face_id[i, j]
                if f < 0:
                    for ch in range(3):
                        colour[ch] += background[ch]
                    continue
                covered += 1
                # Screen-space barycentrics weighted by 1/depth give the perspective-correct ones.
                qa = bary[i, j, 0] * screen[faces[f, 0], 2]
                qb = bary[i, j, 1] * screen[faces[f, 1], 2]
                qc = bary[i, j, 2] * screen[faces[f, 2], 2]
                total = qa + qb + qc
                qa /= total
                qb /= total
                qc /= total
                ta, tb, tc = face_uvs[f, 0], face_uvs[f, 1], face_uvs[f, 2]
                u = qa * uvs[ta, 0] + qb * uvs[tb, 0] + qc * uvs[tc, 0]
                v = qa * uvs[ta, 1] + qb * uvs[tb, 1] + qc * uvs[tc, 1]
                # Texel (row y, column x) has its centre at u = (x + 0.5) / W, v = 1 - (y + 0.5) / H.
                x = min(max(u * tex_w - 0.5, 0.0), tex_w - 1.0)
                y = min(max((1.0 - v) * tex_h - 0.5, 0.0), tex_h - 1.0)
                x0 = min(int(x), max(tex_w - 2, 0))
                y0 = min(int(y), max(tex_h - 2, 0))
                x1 = min(x0 + 1, tex_w - 1)
                y1 = min(y0 + 1, tex_h - 1)
                fx = x - x0
                fy = y - y0
                shade = 1.0
                if use_normals:
                    na, nb, nc = faces[f, 0], faces[f, 1], faces[f, 2]
                    nx = qa * normals[na, 0] + qb * normals[nb, 0] + qc * normals[nc, 0]
                    ny = qa * normals[na, 1] + qb * normals[nb, 1] + qc * normals[nc, 1]
                    nz = qa * normals[na, 2] + qb * normals[nb, 2] + qc * normals[nc, 2]
                    # View ray through the subsample centre, camera frame.
                    rx = K_inv[0, 0] * (j + 0.5) + K_inv[0, 1] * (i + 0.5) + K_inv[0, 2]
                    ry = K_inv[1, 1] * (i + 0.5) + K_inv[1, 2]
                    norm = np.sqrt((nx * nx + ny * ny + nz * nz) * (rx * rx + ry * ry + 1.0))
                    cosine = abs(nx * rx + ny * ry + nz) / norm if norm > 0.0 else 1.0
                    shade = ambient + (1.0 - ambient) * cosine
                w00 = (1.0 - fx) * (1.0 - fy)
                w01 = fx * (1.0 - fy)
                w10 = (1.0 - fx) * fy
                w11 = fx * fy
                for ch in range(3):
                    colour[ch] += shade * (
                        w00 * texture[y0, x0, ch] + w01 * texture[y0, x1, ch]
                        + w10 * texture[y1, x0, ch] + w11 * texture[y1, x1, ch]
                    )  # fmt: skip
            for ch in range(3):
                rgb[pi, pj, ch] = colour[ch] * inv_count
            coverage[pi, pj] = covered * inv_count
    return rgb, coverage


@njit(cache=True, parallel=True)
def _majority_labels(face_id: np.ndarray, face_labels: np.ndarray, s: int, height: int, width: int) -> np.ndarray:
    """(H, W) int32: -1 where the mesh covers under half of the pixel's s x s subsamples, otherwise the
    label most of its covered subsamples see (ties: the one met first in row-major order)."""
    labels = np.empty((height, width), dtype=np.int32)
    for i in prange(height):
        seen = np.empty(s * s, dtype=np.int32)
        for j in range(width):
            n_seen = 0
            for k in range(s * s):
                f = face_id[i * s + k // s, j * s + k % s]
                if f >= 0:
                    seen[n_seen] = face_labels[f]
                    n_seen += 1
            best, best_count = -1, 0
            if 2 * n_seen >= s * s:
                for k in range(n_seen):
                    count = 0
                    for m in range(n_seen):
                        if seen[m] == seen[k]:
                            count += 1
                    if count > best_count:
                        best, best_count = seen[k], count
            labels[i, j] = best
    return labels
