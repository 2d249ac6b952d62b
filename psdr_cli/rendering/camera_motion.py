"""What a moving camera (``parameter: {camera: i, kind: translate|rotate}``) needs from a scene.

With the camera vertex tied to the pixel, a moving camera moves every camera ray: the interior
term follows the first hit along the moving ray (Mitsuba's sensor differentiates ``to_world``),
and *every* discontinuity seen in the image moves relative to the film, static geometry included:

- silhouettes and creases of every mesh (primary term: their projection q(θ) depends on the
  camera through the projection),
- shadow boundaries on every surface (direct and indirect terms: the pixel-tied end point
  x^D(θ) slides across a static visibility boundary; the segment x^D → x^S turns about the fixed
  source point, so it passes the edge at λ·ẋ^D, λ = t_S/(t_S + t_D), which both terms' velocities
  measure: the direct term's lever λ, the indirect term's u2(θ) − x^S).

So every object takes part in the boundary terms, whatever its ``edges`` setting. Shapes that are
not scene objects (the rectangles of area lights) have no edge list; when one of them is in view
its outline is an unhandled image discontinuity, and the gradient is refused.
"""
from __future__ import annotations

from dataclasses import replace

import drjit as dr
import mitsuba as mi
import numpy as np

from ..errors import PsdrError
from ..estimators.camera import Projection


def with_all_edges(scene):
    """The scene with every object's edges in the boundary terms (in place; returns it)."""
    scene.objects = {n: replace(om, edges=True) for n, om in scene.objects.items()}
    return scene


def visible_foreign_shapes(scene, view: int) -> list:
    """Ids of shapes that are not scene objects and have a vertex inside the view's film."""
    proj = Projection(scene.sensors[view])
    out = []
    for shape in scene.mi_scene.shapes():
        if shape.id() in scene.objects or not isinstance(shape, mi.Mesh):
            continue
        with dr.suspend_grad():
            P = dr.unravel(mi.Point3f, dr.detach(shape.vertex_positions_buffer()))
            q, z = proj(P)
        qx, qy, z = (np.asarray(a, float) for a in (q.x, q.y, z))
        inside = (z > proj.near) & (qx >= 0) & (qx <= proj.width) & (qy >= 0) & (qy <= proj.height)
        if inside.any():
            out.append(shape.id())
    return out


def check_camera_motion(scene, view: int):
    """Refuse (one line) a moving camera that sees a shape without an edge list."""
    shapes = visible_foreign_shapes(scene, view)
    if shapes:
        raise PsdrError(f"parameter.camera: shape '{shapes[0]}' (an area light) is in view {view}; the outline of "
                        "a non-object shape is not differentiated when the camera moves (move it out of view)")
