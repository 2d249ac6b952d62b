"""A reconstruction's geometry seen from the held-out cameras against a reference mesh
(``psdr evaluate cfg.yaml --reference MESH``), as Stanford-ORB scores geometry besides Chamfer.

One camera ray through each pixel centre is traced against the recovered mesh and, in a scene of
its own, against the reference (both in the dataset's coordinates). Over the pixels inside the
view's mask (α ≥ ½) where both rays hit, with d the depth along the optical axis and n the
geometric normal turned towards the camera:

    depth error  = min_s mean (s·d_rec − d_ref)² / mean d_ref²
                 = 1 − (Σ d_rec d_ref)² / (Σ d_rec² Σ d_ref²)   (scale-invariant, unit-free),
    normal angle = mean ∠(n_rec, n_ref) in degrees, and the mean cosine distance 1 − n_rec·n_ref.

A reference whose size differs from the reconstruction's by more than :data:`MAX_SIZE_RATIO` (the
longest side of the bounding boxes) is taken to be in other units and refused in one line.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config.scene_ids import sensor_id
from ..errors import PsdrError
from ..estimators.coverage import object_id
from ..estimators.primary import hits_shape
from ..experiment.dataset_frame import to_normalised
from ..scene.build import build_scene

#: Largest ratio of the reference's and the reconstruction's sizes read as the same units.
MAX_SIZE_RATIO = 3.0


@dataclass
class ViewGeometry:
    view: str
    depth_error: float | None
    normal_deg: float | None
    normal_cosine: float | None
    pixels: int


def check_units(reference, mesh, path) -> None:
    """Refuse (one line naming ``path``) a reference whose size is not the reconstruction's to
    within :data:`MAX_SIZE_RATIO`."""
    size = lambda V: float((np.max(V, 0) - np.min(V, 0)).max())  # noqa: E731
    ratio = size(reference[0]) / max(size(mesh[0]), 1e-30)
    if not 1 / MAX_SIZE_RATIO <= ratio <= MAX_SIZE_RATIO:
        raise PsdrError(f"{path}: --reference: it is {ratio:.3g} times the reconstruction's size: in other units "
                        f"than the dataset (expected the same units and frame)")


def depth_and_normals(scene, name: str, view: int) -> tuple:
    """(depth (H, W), normals (H, W, 3), hit (H, W)) of one ray per pixel centre of ``view``: the
    depth along the optical axis and the geometric normal turned towards the camera of the first
    hit, where it is on the object ``name``."""
    width, height = scene.resolution
    sensor = scene.sensors[view]
    with dr.suspend_grad():
        idx = dr.arange(mi.UInt32, width * height)
        pos = mi.Point2f(mi.Float(idx % width) + 0.5, mi.Float(idx // width) + 0.5)
        ray, _ = sensor.sample_ray(0.0, 0.5, pos / mi.ScalarVector2f(width, height), mi.Point2f(0.5))
        si = scene.mi_scene.ray_intersect(ray)
        hit = hits_shape(si, object_id(scene, name))
        forward = mi.traverse(sensor)["to_world"] @ mi.Vector3f(0, 0, 1)
        depth = dr.dot(si.p - ray.o, forward)
        n = dr.select(dr.dot(si.n, ray.d) > 0, -si.n, si.n)
    shape = (height, width)
    normals = np.stack([np.asarray(c, np.float64).reshape(shape) for c in (n.x, n.y, n.z)], -1)
    return np.asarray(depth, np.float64).reshape(shape), normals, np.asarray(hit, bool).reshape(shape)


def view_geometry(name: str, recovered: tuple, reference: tuple, mask) -> ViewGeometry:
    """The scores of one view (module docstring) from :func:`depth_and_normals` of both meshes."""
    (d_r, n_r, h_r), (d_g, n_g, h_g) = recovered, reference
    inside = h_r & h_g & ((np.ones(d_r.shape) if mask is None else np.asarray(mask)) >= 0.5)
    if not inside.any():
        return ViewGeometry(name, None, None, None, 0)
    a, b = d_r[inside], d_g[inside]
    depth = 1.0 - float((a @ b) ** 2 / max(float((a @ a) * (b @ b)), 1e-300))
    cos = np.clip((n_r[inside] * n_g[inside]).sum(-1), -1.0, 1.0)
    return ViewGeometry(name, max(depth, 0.0), float(np.degrees(np.arccos(cos)).mean()), float((1 - cos).mean()),
                        int(inside.sum()))


def reference_scene(test, reference):
    """The held-out experiment ``test``'s scene (without recovered textures: the reference has no
    UVs) with the reference mesh (the dataset's coordinates) in the object's place."""
    V, F = reference
    return build_scene(test, objects={test.optimize.object: (to_normalised(V, test.optimize.target_dataset.frame), F)})


def with_cameras_of(source, target):
    """Give ``target``'s cameras the poses of ``source``'s (e.g. aligned held-out cameras)."""
    src, dst = mi.traverse(source.mi_scene), mi.traverse(target.mi_scene)
    for v in range(len(source.sensors)):
        key = f"{sensor_id(v)}.to_world"
        dst[key] = mi.AffineTransform4f(dr.detach(src[key].matrix))
    dst.update()


def held_out_geometry(scene, test, views, reference) -> list:
    """:class:`ViewGeometry` of every held-out view: ``scene`` holds the recovered mesh, the
    reference (V, F) is traced in a scene of its own, built from ``test`` (its cameras as
    ``scene``'s: aligned cameras are carried over)."""
    ref_scene = reference_scene(test, reference)
    with_cameras_of(scene, ref_scene)
    name = test.optimize.object
    return [view_geometry(view.name, depth_and_normals(scene, name, v), depth_and_normals(ref_scene, name, v),
                          view.mask) for v, view in enumerate(views)]
