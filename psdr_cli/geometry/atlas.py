"""UV atlases for remeshed shapes and the transfer of a texture from the old surface to the new.

A remesh (:mod:`psdr_cli.geometry.remesh`) builds new vertices without texture coordinates. For
``optimize.albedo.texture`` the new mesh is given an atlas by xatlas (:func:`unwrap`: charts cut
along seams, packed into the texture's W × H texels with a gutter; vertices are split at the
seams, one per position/UV pair, as Mitsuba needs them), and the texture is carried over by a
closest-point transfer (:func:`transfer`): for each texel of the new atlas its 3D point on the new
surface, the closest point on the old surface (exact point–triangle distances to the candidate
triangles a KD-tree of centroids proposes), the old UVs interpolated there (barycentric) and the
old texture looked up at them as Mitsuba looks it up (bilinear or nearest, with its wrap mode).
Texels outside every chart take the value of the nearest covered texel, so bilinear lookups
at chart borders do not bleed. Transferring values through 3D points, not UVs, is what makes
seams harmless: a new triangle never straddles two old charts, each texel reads one old point.

UV convention: Mitsuba's, texel (row i, column j) of an (H, W) image is centred at
u = (j + ½)/W, v = (i + ½)/H (v = 0 is the image's top row).
"""
from __future__ import annotations

import numpy as np
import trimesh
import xatlas
from scipy import ndimage
from scipy.spatial import cKDTree

from ..scene.meshes import weld_vertices

#: Texels of gutter around each chart (bilinear lookups at a chart's border stay inside it).
PADDING = 2
#: Old triangles tried per texel (the nearest centroids): the closest point is among them unless
#: the old mesh has long thin triangles far bigger than their neighbours.
CANDIDATES = 16


def unwrap(V, F, size) -> tuple:
    """(V', F', UV) of the mesh (V, F) with an xatlas atlas for a ``size`` = (W, H) texture: V'
    repeats vertices of V at chart seams (V' = V[vmapping]), UV (n', 2) in Mitsuba's convention.
    Deterministic for the same input. A mesh split at old seams is welded first."""
    V, F = weld_vertices(np.asarray(V, np.float64), np.asarray(F, np.int64))
    W, H = size
    atlas = xatlas.Atlas()
    atlas.add_mesh(np.ascontiguousarray(V, np.float32), np.ascontiguousarray(F, np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = int(max(W, H))
    pack.padding = PADDING
    pack.bilinear = True
    atlas.generate(xatlas.ChartOptions(), pack)
    if atlas.atlas_count != 1:
        raise ValueError(f"xatlas made {atlas.atlas_count} atlases (expected one)")
    vmapping, faces, uv = atlas[0]
    if len(faces) != len(F):
        raise ValueError(f"xatlas returned {len(faces)} faces for {len(F)}")
    return V[np.asarray(vmapping, np.int64)], np.asarray(faces, np.int64), np.asarray(uv, np.float64)


def texel_points(V, F, uv, size):
    """(texel rows, texel columns, 3D points) of the texel centres that lie in a triangle of the
    atlas (V, F, uv) of a ``size`` = (W, H) texture (a texel on a shared edge: its first face)."""
    W, H = size
    P = np.asarray(uv, np.float64)[F] * (W, H)  # (m, 3, 2) in texel units
    lo = np.clip(np.floor(P.min(1) - 0.5).astype(np.int64) + 1, 0, (W - 1, H - 1))
    hi = np.clip(np.floor(P.max(1) - 0.5).astype(np.int64), -1, (W - 1, H - 1))
    nx, ny = np.maximum(hi[:, 0] - lo[:, 0] + 1, 0), np.maximum(hi[:, 1] - lo[:, 1] + 1, 0)
    count = nx * ny
    face = np.repeat(np.arange(len(F)), count)
    k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)  # index within the face's box
    col = lo[face, 0] + k % nx[face]
    row = lo[face, 1] + k // nx[face]
    centre = np.stack([col + 0.5, row + 0.5], 1)
    a, b, c = P[face, 0], P[face, 1], P[face, 2]
    d = (b[:, 1] - c[:, 1]) * (a[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (a[:, 1] - c[:, 1])
    ok = np.abs(d) > 1e-12
    d = np.where(ok, d, 1.0)
    w0 = ((b[:, 1] - c[:, 1]) * (centre[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (centre[:, 1] - c[:, 1])) / d
    w1 = ((c[:, 1] - a[:, 1]) * (centre[:, 0] - c[:, 0]) + (a[:, 0] - c[:, 0]) * (centre[:, 1] - c[:, 1])) / d
    w = np.stack([w0, w1, 1 - w0 - w1], 1)
    inside = ok & (w >= -1e-9).all(1)
    face, row, col, w = face[inside], row[inside], col[inside], w[inside]
    _, first = np.unique(row * W + col, return_index=True)
    face, row, col, w = face[first], row[first], col[first], w[first]
    points = np.einsum("ij,ijk->ik", w, np.asarray(V, np.float64)[np.asarray(F)[face]])
    return row, col, points


def closest_uv(V, F, uv, points):
    """The texture coordinates of the closest point on the mesh (V, F, uv) to each of ``points``."""
    V, F, uv = np.asarray(V, np.float64), np.asarray(F, np.int64), np.asarray(uv, np.float64)
    triangles = V[F]
    k = min(CANDIDATES, len(F))
    _, candidates = cKDTree(triangles.mean(1)).query(points, k=k)
    candidates = np.asarray(candidates).reshape(len(points), k)
    flat = candidates.ravel()
    repeated = np.repeat(points, k, axis=0)
    nearest = trimesh.triangles.closest_point(triangles[flat], repeated)
    distance = np.linalg.norm(nearest - repeated, axis=1).reshape(len(points), k)
    best = np.argmin(distance, axis=1)
    pick = np.arange(len(points)) * k + best
    face = flat[pick]
    bary = trimesh.triangles.points_to_barycentric(triangles[face], nearest[pick])
    bary = np.clip(np.nan_to_num(bary, nan=1 / 3), 0.0, 1.0)
    bary /= bary.sum(1, keepdims=True)
    return np.einsum("ij,ijk->ik", bary, uv[F[face]])


def _wrap(i, n, mode: str):
    if mode == "clamp":
        return np.clip(i, 0, n - 1)
    if mode == "mirror":
        i = np.mod(i, 2 * n)
        return np.where(i >= n, 2 * n - 1 - i, i)
    return np.mod(i, n)


def lookup(texture, uv, filter_type: str = "bilinear", wrap_mode: str = "repeat"):
    """Texels of ``texture`` (H, W, C) at ``uv`` (n, 2), as Mitsuba's ``bitmap`` looks them up."""
    texture = np.asarray(texture, np.float64)
    H, W = texture.shape[:2]
    x, y = uv[:, 0] * W, uv[:, 1] * H
    if filter_type == "nearest":
        return texture[_wrap(np.floor(y).astype(np.int64), H, wrap_mode), _wrap(np.floor(x).astype(np.int64), W, wrap_mode)]
    x, y = x - 0.5, y - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    xs = [_wrap(x0, W, wrap_mode), _wrap(x0 + 1, W, wrap_mode)]
    ys = [_wrap(y0, H, wrap_mode), _wrap(y0 + 1, H, wrap_mode)]
    return ((1 - fy) * ((1 - fx) * texture[ys[0], xs[0]] + fx * texture[ys[0], xs[1]])
            + fy * ((1 - fx) * texture[ys[1], xs[0]] + fx * texture[ys[1], xs[1]]))


def fill_gutter(image, covered):
    """``image`` with every texel outside ``covered`` (H, W bool) set to its nearest covered texel."""
    if covered.all() or not covered.any():
        return image
    _, (rows, cols) = ndimage.distance_transform_edt(~covered, return_indices=True)
    return image[rows, cols]


def transfer(old, new_V, new_F, new_uv, texture, filter_type: str = "bilinear", wrap_mode: str = "repeat"):
    """The texture of the atlas (new_V, new_F, new_uv), same size as ``texture`` (H, W, C), from
    ``texture`` on the old mesh ``old`` = (V, F, uv) by closest-point transfer (module docstring)."""
    texture = np.asarray(texture, np.float64)
    H, W = texture.shape[:2]
    row, col, points = texel_points(new_V, new_F, new_uv, (W, H))
    if len(points) == 0:
        raise ValueError("the new atlas covers no texel centre")
    out = np.zeros_like(texture)
    out[row, col] = lookup(texture, closest_uv(*old, points), filter_type, wrap_mode)
    covered = np.zeros((H, W), bool)
    covered[row, col] = True
    out = fill_gutter(out, covered)
    if not np.isfinite(out).all():
        raise ValueError("the transferred texture has NaN or infinite texels")
    return out
