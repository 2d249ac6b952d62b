"""Triangle meshes: procedural shapes, files (PLY/OBJ), validation and object transforms, and
the world-space mesh of each scene object (an XML scene's meshes as Mitsuba loaded them).
Reads mesh files; writes only the decimated Stanford bunny, cached in psdr's cache folder.

Everything here is numpy: a mesh is ``(V, F)`` with ``V`` float64 (n, 3) and ``F`` int64 (m, 3).
"""
from __future__ import annotations

import hashlib
import math
import os
import time
from dataclasses import dataclass
from functools import lru_cache
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np
import pymeshlab
import trimesh

from . import obj_parts
from ..config.experiment_file import Experiment
from ..config.limits import MAX_COORD
from ..config.objects import BitmapConfig, MeshSpec, ObjectConfig, TransformConfig
from ..config.values import Where
from ..errors import ConfigError, PsdrError
from ..support import fileio
from ..support.backend import cache_root


def sphere(radius: float = 1.0, subdivisions: int = 3, resolution: int | None = None):
    """Sphere of the given radius centred at the origin: an icosphere (subdivided icosahedron), or
    with ``resolution`` a UV sphere of ``resolution`` rings × 2·``resolution`` segments."""
    if resolution is not None:
        m = trimesh.creation.uv_sphere(radius=radius, count=[resolution, 2 * resolution])
    else:
        m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


def uv_sphere(radius: float = 1.0, resolution: int = 16):
    """UV sphere with texture coordinates: ``resolution`` rings × 2·``resolution`` segments,
    u = φ/2π (longitude from +x), v = θ/π (colatitude from the north pole z = +r: v = 0, the top
    row of a texture, is north, as in a lat-long map). Returns (V, F, UV); vertices are
    split at the seam u = 0 | 1 and at the poles (one copy per segment), so each vertex has one UV;
    the boundary code welds them by position."""
    rings, segs = resolution, 2 * resolution
    v = np.linspace(0.0, 1.0, rings + 1)
    u = np.linspace(0.0, 1.0, segs + 1)
    U, W = np.meshgrid(u, v)                       # (rings+1, segs+1)
    theta, phi = np.pi * W, 2 * np.pi * U
    V = radius * np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), -np.cos(theta)], -1)
    V[0, :] = (0.0, 0.0, -radius)                  # exact poles
    V[-1, :] = (0.0, 0.0, radius)
    idx = np.arange((rings + 1) * (segs + 1)).reshape(rings + 1, segs + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]   # counter-clockwise seen from outside
    lower = np.stack([a, b, c], -1)[1:]            # the pole rows keep one triangle per segment
    upper = np.stack([a, c, d], -1)[:-1]
    F = np.concatenate([lower.reshape(-1, 3), upper.reshape(-1, 3)]).astype(np.int64)
    used = np.unique(F)
    remap = np.full(idx.size, -1, np.int64)
    remap[used] = np.arange(len(used))
    return V.reshape(-1, 3)[used], remap[F], np.stack([U, 1.0 - W], -1).reshape(-1, 2)[used]


def plane(size=(2.0, 2.0)):
    """Rectangle ``size = (w, h)`` in the z = 0 plane, normal +z."""
    w, h = size[0] / 2, size[1] / 2
    V = np.array([[-w, -h, 0], [w, -h, 0], [w, h, 0], [-w, h, 0]], float)
    F = np.array([[0, 1, 2], [0, 2, 3]], np.int64)
    return V, F


def cube(size=(1.0, 1.0, 1.0)):
    """Axis-aligned box with edge lengths ``size``, centred at the origin."""
    m = trimesh.creation.box(extents=size)
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


def torus(major_radius: float = 1.0, minor_radius: float = 0.3, major_sections: int = 48,
          minor_sections: int = 24):
    """Torus around the z axis."""
    m = trimesh.creation.torus(major_radius=major_radius, minor_radius=minor_radius,
                               major_sections=major_sections, minor_sections=minor_sections)
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


def eared_blob(radius: float = 0.3, ear_length: float = 0.45, ear_width: float = 0.12,
               ear_tilt_deg: float = 25.0, subdivisions: int = 5):
    """A stand-in for thin protrusions: a sphere with two thin, flat ears.

    Every icosphere vertex in direction u is pushed out radially, r(u) = radius + ear_length ·
    Σ_k g(p_k / ear_width, q_k / (2.5·ear_width)), where (p_k, q_k) are u's components across
    ear k's axis a_k (unit vectors tilted ±``ear_tilt_deg`` from +z in the x–z plane; only the
    hemisphere u·a_k > 0) and g(p, q) = exp(−(p² + q²)²) is a flat-topped bump: each ear is a
    finger ≈ 2·ear_width·radius thin (y), 2.5× as wide (x–z) and ``ear_length`` long, with a
    rounded tip. Star-shaped, hence closed and 2-manifold. Centred on the sphere's centre."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    U = np.asarray(m.vertices, float)
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    r = np.full(len(U), float(radius))
    for sign in (-1.0, 1.0):
        t = math.radians(ear_tilt_deg) * sign
        axis = np.array([math.sin(t), 0.0, math.cos(t)])
        across = np.array([math.cos(t), 0.0, -math.sin(t)])  # the ear's wide direction
        p = U @ np.array([0.0, 1.0, 0.0]) / ear_width
        q = U @ across / (2.5 * ear_width)
        r += ear_length * np.exp(-(p * p + q * q) ** 2) * (U @ axis > 0)
    return U * r[:, None], np.asarray(m.faces, np.int64)


def groove_profile(depth: float, height: float, groove_radius: float, segments: int):
    """(y, z_top) of the top edge of a grooved block's cross-section, y from −depth/2 to depth/2:
    z_top = height except over |y| < groove_radius, where a half-cylinder of that radius is cut
    in, z_top = height − √(groove_radius² − y²) (``segments`` points on the arc)."""
    arc = np.linspace(-groove_radius, groove_radius, segments + 1)
    y = np.concatenate([[-depth / 2], arc, [depth / 2]])
    z = np.full(len(y), float(height))
    z[1:-1] = height - np.sqrt(np.maximum(groove_radius ** 2 - arc ** 2, 0.0))
    z[1], z[-2] = height, height  # the rim: sharp creases where the cut meets the top face
    return y, z


def grooved_block(size=(0.9, 0.7, 0.45), groove_radius: float = 0.16, segments: int = 24):
    """A stand-in for a machined part: a box ``size`` = (w, d, h) with a half-cylindrical groove
    of ``groove_radius`` cut along x across its top face, built without booleans.

    The cross-section {(y, z): 0 ≤ z ≤ z_top(y)} (:func:`groove_profile`) is extruded along x
    from −w/2 to w/2. Each end cap is the strip of quads between consecutive profile columns
    (y_i, 0)–(y_i, z_top(y_i)), so all its vertices lie on its boundary loop, which the side
    walls share: the mesh is closed, with sharp creases at the box edges and the groove's rims
    and a concave groove. Centred on the origin in x/y, resting on z = 0."""
    w, d, h = (float(x) for x in size)
    y, z = groove_profile(d, h, groove_radius, segments)
    n = len(y)
    # profile loop: bottom points left→right, then top points right→left
    loop = np.concatenate([np.stack([y, np.zeros(n)], -1), np.stack([y, z], -1)[::-1]])
    m = len(loop)
    V = np.concatenate([np.column_stack([np.full(m, -w / 2), loop]), np.column_stack([np.full(m, w / 2), loop])])
    faces = []
    for i in range(m):  # side walls between the two copies of the loop
        j = (i + 1) % m
        faces += [[i, j, m + j], [i, m + j, m + i]]
    for i in range(n - 1):  # end caps: quad (bottom_i, bottom_i+1, top_i+1, top_i)
        b0, b1, t1, t0 = i, i + 1, 2 * n - 2 - i, 2 * n - 1 - i
        faces += [[b0, t0, t1], [b0, t1, b1]]
        faces += [[m + b0, m + b1, m + t1], [m + b0, m + t1, m + t0]]
    mesh = trimesh.Trimesh(V, np.asarray(faces, np.int64), process=True)
    mesh.fix_normals()
    return np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)


def bunny_path() -> Path:
    """The Stanford-bunny sample shipped inside the installed pymeshlab wheel."""
    path = Path(pymeshlab.__file__).parent / "tests" / "sample_meshes" / "bunny.obj"
    if not path.exists():
        raise FileNotFoundError(f"the pymeshlab package has no bunny sample at {path}")
    return path


def bunny(size: float = 1.0, faces: int = 5000):
    """Stanford bunny, decimated to about ``faces`` triangles with pymeshlab's quadric edge collapse,
    turned z-up, centred on the origin in x/y, resting on z = 0, longest side ``size``."""
    V, F = decimated_bunny(int(faces))
    lo, hi = V.min(0), V.max(0)
    V = (V - [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]]) * (size / (hi - lo).max())
    return V, F.copy()


@lru_cache(maxsize=8)
def decimated_bunny(faces: int):
    """The shipped bunny sample decimated to about ``faces`` triangles and turned z-up, unscaled
    (read-only arrays). The decimation is a pure function of ``faces`` (and of pymeshlab and its
    sample) and takes seconds, while one run builds the same mesh for its targets, its scene and
    its evaluation: it is remembered per process and on disk (:func:`cached_bunny_path`)."""
    path = cached_bunny_path(faces)
    mesh = read_cached_bunny(path)
    if mesh is None:
        mesh = decimate_bunny(faces)
        write_cached_bunny(path, *mesh)
    V, F = mesh
    V.flags.writeable = F.flags.writeable = False
    return V, F


#: pymeshlab's quadric edge collapse as the bunny is decimated (part of the cache key).
BUNNY_DECIMATION = {"preservenormal": True, "preservetopology": True, "qualitythr": 0.5}
#: The sample's y-up axes made z-up: x→y, y→z, z→x (part of the cache key).
BUNNY_Z_UP = (2, 0, 1)
#: Cached files larger than this are not read (the full sample is about 2 MB).
MAX_CACHED_BUNNY_BYTES = 64 << 20
#: A temporary of the cache folder this old is a killed writer's (:func:`write_cached_bunny`).
STALE_TEMPORARY_SECONDS = 600


def decimate_bunny(faces: int):
    """(V, F) of the bunny sample after pymeshlab's quadric edge collapse to ``faces`` triangles
    (none when it has fewer), turned z-up."""
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(bunny_path()))
    if ms.current_mesh().face_number() > faces:
        ms.meshing_decimation_quadric_edge_collapse(targetfacenum=faces, **BUNNY_DECIMATION)
    m = ms.current_mesh()
    V = np.asarray(m.vertex_matrix(), float)[:, list(BUNNY_Z_UP)]
    F = np.asarray(m.face_matrix(), np.int64)
    return V, F


def cached_bunny_path(faces: int) -> Path | None:
    """``<cache root>/meshes/bunny-<faces>-<key>.npz``, the key a digest of pymeshlab's version,
    the sample's size and the decimation's settings, so that a change of any gives a new file
    (:func:`psdr_cli.support.backend.cache_root`); None (no cache) when pymeshlab's version is unknown."""
    try:
        pymeshlab_version = version("pymeshlab")
    except PackageNotFoundError:
        return None
    what = repr((pymeshlab_version, bunny_path().stat().st_size, sorted(BUNNY_DECIMATION.items()), BUNNY_Z_UP))
    key = hashlib.sha1(what.encode()).hexdigest()[:12]
    return Path(cache_root()) / "meshes" / f"bunny-{faces}-{key}.npz"


def read_cached_bunny(path: Path | None):
    """(V, F) from ``path``, or None when there is no cache or the file is not a valid mesh
    (damaged in any way, too large, non-finite, indices out of range): the bunny is then
    decimated again. Reading a cache never fails a command."""
    if path is None:
        return None
    try:
        if path.stat().st_size > MAX_CACHED_BUNNY_BYTES:
            return None
        with np.load(path, allow_pickle=False) as data:
            V, F = np.array(data["V"]), np.array(data["F"])
    except Exception:  # noqa: BLE001 (missing, truncated, not an .npz, bad compression, ...)
        return None
    ok = (V.dtype == np.float64 and V.ndim == 2 and V.shape[1] == 3 and len(V) >= 3 and np.isfinite(V).all()
          and F.dtype == np.int64 and F.ndim == 2 and F.shape[1] == 3 and len(F) > 0
          and F.min() >= 0 and F.max() < len(V))
    return (V, F) if ok else None


def write_cached_bunny(path: Path | None, V, F) -> None:
    """Leave (V, F) in ``path`` (atomically: a reader sees the whole file or none); a cache that
    cannot be written is skipped, the mesh is still returned. Temporaries of writers killed
    mid-write, older than :data:`STALE_TEMPORARY_SECONDS`, are removed first (another process may
    be writing its own right now: a write takes milliseconds)."""
    if path is None:
        return
    now = time.time()
    for tmp in fileio.temporaries(path.parent):
        try:
            if now - tmp.stat().st_mtime > STALE_TEMPORARY_SECONDS:
                tmp.unlink()
        except OSError:
            pass
    try:
        with fileio.atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, V=V, F=F)
    except PsdrError:
        pass


#: A plane's UVs: the texture upright seen from +z (v = 0, its top row, at +y).
PLANE_UV = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], float)


def procedural(shape: str, params: dict):
    """Mesh (V, F) for ``{shape: ..., **params}`` of the experiment file."""
    return procedural_uv(shape, params)[:2]


def procedural_uv(shape: str, params: dict):
    """(V, F, UV) for ``{shape: ..., **params}``: UV is None except for a plane ([0, 1]² over its
    extent) and a sphere with ``uv: true`` (:func:`uv_sphere`)."""
    if shape == "sphere" and params.get("uv"):
        p = {k: v for k, v in params.items() if k != "uv"}
        return uv_sphere(p.get("radius", 1.0), p.get("resolution", 16))
    if shape == "plane":
        return (*plane(**params), PLANE_UV.copy())
    params = {k: v for k, v in params.items() if k != "uv"}
    if shape == "sphere":
        return (*sphere(**params), None)
    return (*_procedural(shape, params), None)


def _procedural(shape: str, params: dict):
    if shape == "sphere":
        return sphere(**params)
    if shape == "plane":
        return plane(**params)
    if shape == "cube":
        return cube(**params)
    if shape == "torus":
        return torus(**params)
    if shape == "bunny":
        return bunny(**params)
    if shape == "eared_blob":
        return eared_blob(**params)
    if shape == "grooved_block":
        return grooved_block(**params)
    raise ValueError(shape)


def read_mesh_file(path: Path):
    """Vertices and triangles of a PLY or OBJ file, unprocessed (no merging, no reordering)."""
    return read_mesh_file_uv(path)[:2]


def read_mesh_file_uv(path: Path):
    """(V, F, UV) of a PLY or OBJ file, unprocessed; UV (n, 2) are the per-vertex texture
    coordinates as Mitsuba's own loaders read them (OBJ ``vt`` with v flipped, split into one
    vertex per position/UV pair; PLY ``s, t`` or ``u, v`` as stored), or None when the file has
    none. In Mitsuba's convention v = 0 is the top row of a texture image. An OBJ's material
    library is not read here (its ``Kd`` colours: :mod:`psdr_cli.scene.obj_parts`): trimesh would
    invent UVs for a file without ``vt`` and pack the UVs of several materials into an atlas."""
    obj = Path(path).suffix.lower() == ".obj"
    if obj:
        try:
            Path(path).read_bytes().decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ValueError(f"not a text OBJ file (byte {exc.start} is not UTF-8)") from None
    mesh = trimesh.load(str(path), force="mesh", process=False, **({"skip_materials": True} if obj else {}))
    V, F = np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)
    uv = getattr(mesh.visual, "uv", None)
    uv = None if uv is None or len(uv) != len(V) else np.array(uv, float).reshape(-1, 2)
    if uv is not None and obj:
        uv[:, 1] = 1.0 - uv[:, 1]  # as Mitsuba's OBJ loader: vt's v runs up the image, Mitsuba's down
    return V, F, uv


def face_areas(V, F):
    """Triangle areas ½|(v1 − v0) × (v2 − v0)|."""
    return 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)


def degenerate_faces(V, F, rel_eps: float = 1e-12):
    """Mask of faces whose area is below rel_eps·(bounding-box diagonal)² or with a repeated index."""
    diag2 = float(np.sum((V.max(0) - V.min(0)) ** 2)) or 1.0
    repeated = (F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 0] == F[:, 2])
    return repeated | (face_areas(V, F) <= rel_eps * diag2)


def load_mesh(spec: MeshSpec, file: str):
    """Mesh (V, F) of an object's ``mesh:`` entry, validated. Errors name ``file`` and the key path."""
    return load_mesh_uv(spec, file)[:2]


def load_mesh_uv(spec: MeshSpec, file: str, keep_uv: bool = True):
    """(V, F, UV) of an object's ``mesh:`` entry, validated; UV is None for a mesh without texture
    coordinates. A file mesh with UVs keeps one vertex per position/UV pair (split at UV seams, as
    Mitsuba needs them) when ``keep_uv``; otherwise (and without UVs) it is welded by position
    and its UVs dropped, like an untextured object's."""
    where = Where(file, spec.key)
    uv = None
    if spec.file is not None:
        if not spec.file.exists():
            raise where.fail(f"mesh file not found: {spec.file}")
        if spec.file.suffix.lower() not in (".ply", ".obj"):
            raise where.fail(f"unsupported mesh format '{spec.file.suffix}' (expected .ply or .obj)")
        if not os.access(spec.file, os.R_OK):
            raise where.fail(f"mesh file is not readable: {spec.file}")
        try:
            if spec.part is None:
                V, F, uv = read_mesh_file_uv(spec.file)
                uv = uv if keep_uv else None
            else:
                V, F = obj_parts.read_part(spec.file, spec.part)
        except KeyError as exc:
            raise where.fail(exc.args[0]) from None
        except Exception as exc:  # noqa: BLE001 - any parser failure is a bad file
            msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise where.fail(f"cannot read mesh {spec.file.name}: {msg}") from None
        if uv is not None and not np.isfinite(uv).all():
            raise where.fail(f"mesh {spec.file.name} has NaN or infinite texture coordinates")
        if len(V) and np.isfinite(V).all():
            V, F, uv = weld_vertices_uv(V, F, uv)
    else:
        V, F, uv = procedural_uv(spec.shape, spec.params)
    return validate_mesh_uv(V, F, uv, where, spec.repair)


def weld(V, rel_tol: float = 1e-7):
    """Map vertices at the same position (within rel_tol·extent) to one id.

    Returns (welded_id per vertex, representative vertex per welded id). Welded ids follow the
    order of first appearance, so a mesh without duplicates keeps its numbering."""
    V = np.asarray(V, float)
    extent = float(np.abs(V).max()) or 1.0
    key = np.round(V / (extent * rel_tol)).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rank[inverse.reshape(-1)], first[order]


def weld_vertices(V, F):
    """Merge vertices at the same position (files split them at UV/normal seams), so that every
    edge has both its faces and each surface point has one set of parameters to optimise."""
    wid, rep = weld(V)
    return V[rep], wid[F]


def weld_vertices_uv(V, F, uv=None):
    """:func:`weld_vertices` for a mesh with texture coordinates ``uv`` (n, 2): only vertices with
    the same position and the same UV are merged, so UV seams stay split. (V, F, uv)."""
    if uv is None:
        return (*weld_vertices(V, F), None)
    V = np.asarray(V, float)
    extent = float(np.abs(V).max()) or 1.0
    wid, rep = weld(np.concatenate([V, np.asarray(uv, float) * extent], axis=1))
    return V[rep], wid[F], np.asarray(uv, float)[rep]


def validate_mesh(V, F, where: Where, repair: bool = False):
    """Reject empty meshes, non-finite vertices, bad indices and (unless ``repair``) degenerate faces."""
    return validate_mesh_uv(V, F, None, where, repair)[:2]


def validate_mesh_uv(V, F, uv, where: Where, repair: bool = False):
    """:func:`validate_mesh` with per-vertex texture coordinates ``uv`` (or None), kept in step
    with the vertices a repair drops: (V, F, uv)."""
    V = np.asarray(V, float).reshape(-1, 3)
    F = np.asarray(F, np.int64).reshape(-1, 3)
    if len(V) == 0 or len(F) == 0:
        raise where.fail(f"mesh is empty ({len(V)} vertices, {len(F)} triangles)")
    bad = ~np.isfinite(V).all(axis=1)
    if bad.any():
        raise where.fail(f"mesh has {int(bad.sum())} vertices with NaN or infinite coordinates")
    far = (np.abs(V) > MAX_COORD).any(axis=1)
    if far.any():
        raise where.fail(f"mesh has {int(far.sum())} vertices with coordinates beyond ±{MAX_COORD:g} "
                         f"(e.g. {V[far][0].tolist()}; float32 rendering needs smaller values)")
    if F.min() < 0 or F.max() >= len(V):
        raise where.fail(f"mesh has face indices outside 0..{len(V) - 1}")
    degenerate = degenerate_faces(V, F)
    if degenerate.any():
        if not repair:
            raise where.fail(f"mesh has {int(degenerate.sum())} degenerate (zero-area) triangles "
                             f"of {len(F)}; fix the file or set 'repair: true' to drop them")
        F = F[~degenerate]
        if len(F) == 0:
            raise where.fail("mesh has only degenerate triangles")
        used = np.unique(F)
        remap = np.full(len(V), -1, np.int64)
        remap[used] = np.arange(len(used))
        V, F = V[used], remap[F]
        if uv is not None:
            uv = np.asarray(uv, float)[used]
    return V, F, uv


def rotation_matrix(axis, angle_deg: float):
    """Rodrigues rotation R = I + sinθ K + (1 − cosθ) K² about the unit ``axis``."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = math.radians(angle_deg)
    return np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * (K @ K)


def transform_matrix(t: TransformConfig) -> np.ndarray:
    """4×4 matrix T·R·S: scale first, then rotate, then translate."""
    M = np.eye(4)
    M[:3, :3] = rotation_matrix(t.rotate_axis, t.rotate_deg) @ np.diag(t.scale)
    M[:3, 3] = t.translate
    return M


def apply_transform(V, M):
    """Points V (n, 3) mapped by the affine 4×4 matrix M."""
    return V @ M[:3, :3].T + M[:3, 3]


def write_ply(path, V, F, uv=None):
    """Binary PLY without normals or colours (opens in MeshLab and Blender), with per-vertex
    texture coordinates ``uv`` (n, 2) as ``s, t`` when given (Mitsuba's convention, read back as
    stored); refuses non-finite vertices."""
    if not np.isfinite(np.asarray(V, float)).all():
        bad = int((~np.isfinite(np.asarray(V, float))).any(axis=1).sum())
        raise PsdrError(f"{path}: not written: the mesh has {bad} vertices with NaN or infinite coordinates")
    visual = None if uv is None else trimesh.visual.TextureVisuals(uv=np.asarray(uv, np.float64))
    trimesh.Trimesh(V, F, process=False, visual=visual).export(str(path), file_type="ply")


# --------------------------------------------------------------------------------------------
# Scene objects: world-space meshes as built (procedural, file or XML meshes, transformed)
# --------------------------------------------------------------------------------------------
@dataclass
class ObjectMesh:
    """World-space geometry of one scene object as built (before any optimisation)."""
    name: str
    vertices: np.ndarray
    faces: np.ndarray
    edges: bool
    config: ObjectConfig
    uv: np.ndarray | None = None   # per-vertex texture coordinates (n, 2), when the mesh has them


def object_geometry(obj: ObjectConfig, geometry: dict):
    """World-space (V, F) of an XML object, from ``geometry`` (``scene.mitsuba.geometry``: the
    XML's meshes as :func:`psdr_cli.scene.mitsuba_xml.scene_config` read them at load)."""
    if obj.name not in geometry:
        raise ConfigError(obj.mesh.key, "", "the XML scene has not been read (load the experiment with "
                          "psdr_cli.experiment.load.load_experiment)")
    return geometry[obj.name]


def xml_geometry(scene) -> dict:
    """{id: (V, F)} of the meshes of a scene's XML as read at load (empty without an XML)."""
    return scene.mitsuba.geometry if scene.mitsuba is not None else {}


def has_bitmap(obj: ObjectConfig) -> bool:
    """Whether the object's BSDF has a bitmap texture (and so needs UV coordinates)."""
    return any(isinstance(v, BitmapConfig) for v in obj.bsdf.params.values())


def object_mesh(obj: ObjectConfig, file: str, geometry: dict):
    """World-space (V, F) of an object: its mesh, validated, then its transform (an XML scene's
    mesh: as Mitsuba loaded it, in world space, from ``geometry``: :func:`xml_geometry`)."""
    return object_mesh_uv(obj, file, geometry)[:2]


def object_mesh_uv(obj: ObjectConfig, file: str, geometry: dict):
    """:func:`object_mesh` with the mesh's per-vertex texture coordinates: (V, F, UV or None); a
    file mesh keeps its UVs (and its seam-split vertices) only when the BSDF has a bitmap."""
    if obj.mesh.shape == "mitsuba":
        return (*object_geometry(obj, geometry), None)
    V, F, uv = load_mesh_uv(obj.mesh, file, keep_uv=has_bitmap(obj))
    V = apply_transform(V, transform_matrix(obj.transform))
    return V, F, uv


def build_objects(exp: Experiment) -> dict:
    """World-space meshes of every object, validated (no Mitsuba needed)."""
    out = {}
    for obj in exp.scene.objects:
        V, F, uv = object_mesh_uv(obj, str(exp.file), xml_geometry(exp.scene))
        out[obj.name] = ObjectMesh(obj.name, V, F, obj.edges, obj, uv)
    return out
