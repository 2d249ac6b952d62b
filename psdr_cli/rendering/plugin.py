"""Which shapes the Mitsuba plugin (``type: psdr``) differentiates, from a scene and whatever
``params`` a caller hands to ``render_forward`` / ``render_backward`` / ``mi.render``.

Mitsuba users pass a full ``mi.SceneParameters``, one reduced with ``params.keep([key])``, or (as
Mitsuba's own AD tests do) the latent variable θ itself after pushing its gradient into the scene
with ``dr.forward(θ, dr.ADFlag.ClearEdges)``. The scene's shapes and sensors hold the current
(AD-attached) buffers in every case, so differentiability is read from the shapes themselves:

- a triangle mesh whose vertex buffer carries gradients gets boundary terms;
- a sensor whose ``to_world`` carries gradients moves every discontinuity in its image, so every
  mesh gets boundary terms (see :mod:`psdr_cli.rendering.camera_motion`);
- any other shape with a gradient-carrying geometric parameter (a ``sphere``'s centre or radius,
  a ``rectangle``'s ``to_world``, …) has discontinuities the plugin cannot move: one warning
  names it.
"""
from __future__ import annotations

import warnings
from types import SimpleNamespace

import drjit as dr
import mitsuba as mi
import numpy as np

from ..estimators.boundary_sampling import TRANSMISSIVE
from ..geometry.shading import transmits
from ..scene.meshes import ObjectMesh

#: Geometric parameters of non-mesh shapes (and of meshes, besides their vertex buffer).
GEOMETRY_KEYS = ("to_world", "center", "radius")


def grad_enabled(value) -> bool:
    return dr.grad_enabled(value.matrix if isinstance(value, (mi.AffineTransform4f, mi.Transform4f)) else value)


def sensor_moves(sensor) -> bool:
    """Whether the sensor's ``to_world`` carries gradients."""
    params = mi.traverse(sensor)
    return "to_world" in params and grad_enabled(params["to_world"])


def mesh_moves(shape) -> bool:
    return isinstance(shape, mi.Mesh) and dr.grad_enabled(shape.vertex_positions_buffer())


def object_mesh(shape) -> ObjectMesh:
    """The shape's current geometry as an :class:`ObjectMesh` (read from the shape, not from
    ``params``, so reduced parameter sets work)."""
    V = np.asarray(dr.detach(shape.vertex_positions_buffer()), np.float64).reshape(-1, 3)
    F = np.asarray(shape.faces_buffer(), np.int64).reshape(-1, 3)
    bsdf = shape.bsdf()
    transmissive = bsdf is not None and mi.has_flag(bsdf.flags(), mi.BSDFFlags.Transmission)
    cfg = SimpleNamespace(smooth=shape.has_vertex_normals(),
                          bsdf=SimpleNamespace(type=TRANSMISSIVE[0] if transmissive else "opaque"))
    return ObjectMesh(shape.id(), V, F, True, cfg)


def undifferentiated_shapes(scene: mi.Scene) -> list:
    """Ids of shapes with gradient-carrying geometry the plugin does not differentiate."""
    out = []
    for shape in scene.shapes():
        if mesh_moves(shape) and "vertex_positions" in mi.traverse(shape):
            continue
        params = mi.traverse(shape)
        if any(k in params and grad_enabled(params[k]) for k in GEOMETRY_KEYS):
            out.append(shape.id())
    return out


def differentiable_meshes(scene: mi.Scene, sensor) -> dict:
    """{shape id: ObjectMesh} of the meshes that get boundary terms for this sensor, warning once
    per call about shapes that carry gradients but cannot be differentiated."""
    bad = undifferentiated_shapes(scene)
    if bad:
        warnings.warn(f"psdr integrator: shape(s) {', '.join(repr(b) for b in bad)} carry gradients in a "
                      "parameter the plugin cannot differentiate (only mesh vertex positions and sensor "
                      "to_world are); their boundary terms are missing", stacklevel=3)
    every = sensor_moves(sensor)
    out = {s.id(): object_mesh(s) for s in scene.shapes()
           if isinstance(s, mi.Mesh) and "vertex_positions" in mi.traverse(s) and (every or mesh_moves(s))}
    shapes = {s.id(): s for s in scene.shapes()}
    smooth = [n for n, om in out.items() if om.config.smooth and transmits(shapes[n].bsdf())]
    if smooth:
        warnings.warn(f"psdr integrator: mesh(es) {', '.join(repr(n) for n in smooth)} have vertex normals and a "
                      "transmitting BSDF; the terminator term covers reflection only (psdr_cli.geometry.shading)",
                      stacklevel=3)
    return out
