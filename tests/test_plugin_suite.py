"""Scenes modelled on Mitsuba 3's own AD test suite (its discontinuous configurations: moving
occluder, shadow receiver, self-shadowing right angle, moving rectangle and sphere emitters, a
scaled emitter, a constant-lit rectangle, a plane under an environment map, a translated camera),
rebuilt procedurally with ``mi.load_dict`` and rendered through the ``type: psdr`` plugin.

Each gradient is taken the way Mitsuba's tests take it: θ = 0 with gradients enabled, the scene
updated from θ, ``dr.forward(θ, dr.ADFlag.ClearEdges)``, then
``integrator.render_forward(scene, params=θ)``. It is compared with central finite differences of
the plugin's own render (common random numbers, 8 batches on both sides) under the shared verdict
(:func:`psdr_cli.support.verdict.agrees`: image sum and 4×4 tiles). The FD step is 0.003 (≈ 0.03 px of
edge motion): at 0.01 an edge within 0.1 px of a tile border leaks into the next tile's FD, where
the derivative at θ = 0 is exactly 0.

Geometry follows Mitsuba's configurations where that leaves enough discontinuity in a 32×32 image
for the tile statistics (≥ 10 signal tiles); otherwise lights and shapes are enlarged or turned.
"""
from __future__ import annotations

import warnings

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from psdr_cli.rendering.integrator import register
from psdr_cli.rendering.reference import agreement
from psdr_cli.scene import meshes
from psdr_cli.scene.mitsuba_xml import mesh
from psdr_cli.support.backend import select_variant
from psdr_cli.support.verdict import agrees, describe

RES = 32
BATCHES = 8


@pytest.fixture(scope="module", autouse=True)
def plugin():
    """An AD variant with the ``psdr`` integrator registered."""
    select_variant("auto")
    register()
    mi.set_log_level(mi.LogLevel.Error)


# ---- procedural geometry ---------------------------------------------------------------------

def transformed(V, matrix) -> np.ndarray:
    """Vertices (n, 3) under a 4×4 affine matrix."""
    M = np.asarray(matrix, np.float64)
    return V @ M[:3, :3].T + M[:3, 3]


def rectangle(to_world=None):
    """Mitsuba's rectangle, [-1, 1]² in z = 0 facing +z, as two triangles in world space."""
    V, F = meshes.plane((2.0, 2.0))
    return (V if to_world is None else transformed(V, np.array(to_world.matrix))), F


def ball(center, radius, subdivisions=2):
    """A flat-shaded icosphere."""
    V, F = meshes.sphere(radius, subdivisions)
    return V + np.asarray(center, np.float64), F


def diffuse(reflectance=0.5) -> mi.BSDF:
    return mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": reflectance}})


def shape(name, VF, bsdf=None, radiance=None) -> mi.Mesh:
    """A flat-shaded ``mi.Mesh`` with a diffuse BSDF, or (``radiance``) a black area emitter."""
    if radiance is None:
        return mesh(name, *VF, bsdf or diffuse())
    emitter = mi.load_dict({"type": "area", "radiance": {"type": "rgb", "value": radiance}})
    return mesh(name, *VF, diffuse(0.0), emitter=emitter)


def sensor(origin=(0, 0, 4), target=(0, 0, 0), up=(0, 1, 0), fov=39.3) -> dict:
    """Mitsuba's test camera: perspective, box-filtered RGB film of RES × RES."""
    return {"type": "perspective", "fov": fov, "to_world": mi.ScalarTransform4f().look_at(origin=origin, target=target, up=up),
            "film": {"type": "hdrfilm", "width": RES, "height": RES, "pixel_format": "rgb",
                     "rfilter": {"type": "box"}},
            "sampler": {"type": "independent"}}


def scene(**shapes) -> mi.Scene:
    """``mi.load_dict`` of the shapes (and emitters) with the test camera unless one is given."""
    shapes.setdefault("sensor", sensor())
    return mi.load_dict({"type": "scene", **shapes})


# ---- how θ enters the scene ------------------------------------------------------------------

def translate_vertices(params, keys, axis):
    """update(θ): the vertex buffers of ``keys`` translated by θ·axis."""
    initial = {k: mi.Float(params[k]) for k in keys}

    def update(theta):
        for k in keys:
            params[k] = dr.ravel(dr.unravel(mi.Point3f, initial[k]) + mi.Vector3f(*axis) * theta)
        params.update()
    return update


def scale_vertices(params, key):
    """update(θ): the vertex buffer of ``key`` scaled by 1 + θ about the origin."""
    initial = mi.Float(params[key])

    def update(theta):
        params[key] = initial * (1.0 + theta)
        params.update()
    return update


def translate_sensor(params, key, axis):
    """update(θ): the sensor moved by θ·axis in its own frame (to_world · translate)."""
    initial = mi.Transform4f(params[key])

    def update(theta):
        params[key] = initial @ mi.Transform4f().translate(mi.Vector3f(*axis) * theta)
        params.update()
    return update


# ---- the two sides of the comparison ---------------------------------------------------------

def psdr_integrator(max_depth, spp_boundary=None) -> mi.Integrator:
    props = {"type": "psdr", "max_depth": max_depth}
    if spp_boundary:
        props.update(primary_spp=spp_boundary, boundary_spp=spp_boundary)
    return mi.load_dict(props)


def forward_batches(sc, update, integrator, spp) -> list:
    """Per-seed gradient images dI/dθ at θ = 0 (``spp`` each), in the form Mitsuba's AD tests use."""
    out = []
    for b in range(BATCHES):
        theta = mi.Float(0.0)
        dr.enable_grad(theta)
        update(theta)
        dr.forward(theta, dr.ADFlag.ClearEdges)
        out.append(np.asarray(integrator.render_forward(sc, params=theta, spp=spp, seed=1000 + b), np.float64))
        update(mi.Float(0.0))
    return out


def fd_batches(sc, update, integrator, h, spp) -> list:
    """Per-seed central differences [I(h) − I(−h)] / 2h of the plugin's render (``spp`` each), the
    same seed on both sides."""
    out = []
    for b in range(BATCHES):
        images = []
        for sign in (1.0, -1.0):
            update(mi.Float(sign * h))
            images.append(np.asarray(integrator.render(sc, seed=77 + b, spp=spp), np.float64))
        out.append((images[0] - images[1]) / (2 * h))
    update(mi.Float(0.0))
    return out


def fd_agreement(sc, update, max_depth, spp, h, fd_spp, spp_boundary=None) -> dict:
    """Agreement statistics (psdr_cli.rendering.reference.agreement) of the plugin's gradient with FD;
    sample counts are per batch, and no warning may be raised (no shape silently left out)."""
    integrator = psdr_integrator(max_depth, spp_boundary)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no shape of these scenes may be silently undifferentiated
        grad = forward_batches(sc, update, integrator, spp)
    fd = fd_batches(sc, update, integrator, h, fd_spp)
    return agreement([(grad, None)], fd)


def assert_agrees(stats):
    s = stats["sum"]
    assert agrees(stats), (f"psdr {s['estimate']:+.3g} ± {s['estimate_se']:.2g} vs FD {s['fd']:+.3g} ± "
                           f"{s['fd_se']:.2g}\n" + describe(stats))


# ---- the scenes ------------------------------------------------------------------------------

def occluder_scene():
    """A ball between a small bright spherical light and a diffuse square facing the camera: its
    shadow falls in the middle of the square, the ball itself is out of view."""
    return scene(plane=shape("plane", rectangle()),
                 occluder=shape("occluder", ball([2.0, 0.0, 2.0], 0.35)),
                 light=shape("light", ball([4.0, 0.0, 4.0], 0.08, 1), radiance=400.0))


def right_angle_scene():
    """A wall and a floor at a right angle under a rectangular light above and behind the wall,
    which shadows the front of the floor; seen from close by with a wide lens."""
    look_at = mi.ScalarTransform4f().look_at
    return scene(wall=shape("wall", rectangle(look_at(origin=[0, 0, -1], target=[0, 0, 0], up=[0, 1, 0])),
                            diffuse([0.1, 0.1, 0.4])),
                 floor=shape("floor", rectangle(look_at(origin=[0, -1, -1], target=[0, 0, -1], up=[0, 0, 1])),
                             diffuse([0.4, 0.1, 0.1])),
                 light=shape("light", rectangle(mi.ScalarTransform4f().translate([0, 8, -4])
                                                @ mi.ScalarTransform4f().scale([2, 0.5, 1])), radiance=10.0),
                 sensor=sensor(origin=(0, 0, 1), target=(0, 0, -1), fov=87))


def tilted_rectangle():
    """A 1.4-wide square turned 30° about the view axis, so its moving edges cross many tiles."""
    return rectangle(mi.ScalarTransform4f().translate([0.2, 0.1, 0]) @ mi.ScalarTransform4f().rotate([0, 0, 1], 30)
                     @ mi.ScalarTransform4f().scale(0.7))


def sky(width=32, height=16) -> mi.Bitmap:
    """A procedural environment: blue zenith fading to a warm horizon, brighter towards +x."""
    v = (np.arange(height)[:, None] + 0.5) / height
    u = (np.arange(width)[None, :] + 0.5) / width
    glow = 1 + 0.8 * np.cos(2 * np.pi * u)
    img = np.stack([0.4 + 0.8 * v * glow, 0.5 + 0.5 * v * glow, 1.0 - 0.4 * v + 0 * u], -1)
    return mi.Bitmap(img.astype(np.float32))


# ---- tests -------------------------------------------------------------------------------------

def test_translate_occluder():
    """TranslateOccluderAreaLight: the ball moves sideways, its shadow on the square with it."""
    sc = occluder_scene()
    update = translate_vertices(mi.traverse(sc), ["occluder.vertex_positions"], (1, 0, 0))
    assert_agrees(fd_agreement(sc, update, 2, 64, 0.003, 1024))


def test_translate_shadow_receiver():
    """TranslateShadowReceiverAreaLight: the lit square slides under a fixed shadow; its outline
    moves, the shadow does not. The step is 0.01 here: at 0.003 float32 rounding of the shifted
    plane leaves a systematic FD of ≈ 2·10⁻⁶ on a shadowed tile where the derivative is 0 (the
    largest tiles are ≈ 5), which the verdict then counts as a 7σ signal tile."""
    sc = occluder_scene()
    update = translate_vertices(mi.traverse(sc), ["plane.vertex_positions"], (1, 0, 0))
    assert_agrees(fd_agreement(sc, update, 2, 64, 0.01, 1024))


def test_translate_self_shadowing_right_angle():
    """TranslateSelfShadowingRightAngle: wall and floor move together towards the camera; the wall's
    shadow on the floor moves with them."""
    sc = right_angle_scene()
    update = translate_vertices(mi.traverse(sc), ["wall.vertex_positions", "floor.vertex_positions"], (0, 0, 1))
    assert_agrees(fd_agreement(sc, update, 2, 64, 0.003, 1024))


def test_translate_rectangle_emitter_on_black():
    """TranslateRectangleEmitterOnBlack (turned 30°): only the emitter's outline carries gradient."""
    sc = scene(light=shape("light", tilted_rectangle(), radiance=1.0))
    update = translate_vertices(mi.traverse(sc), ["light.vertex_positions"], (1, 0, 0))
    assert_agrees(fd_agreement(sc, update, 2, 64, 0.003, 1024))


def test_translate_sphere_emitter_on_black():
    """TranslateSphereEmitterOnBlack, the sphere as a triangle mesh (the plugin's only shape)."""
    sc = scene(light=shape("light", ball([0.1, 0.0, 0.0], 0.7), radiance=1.0))
    update = translate_vertices(mi.traverse(sc), ["light.vertex_positions"], (1, 0, 0))
    assert_agrees(fd_agreement(sc, update, 2, 64, 0.003, 1024))


def test_scale_sphere_emitter_on_black():
    """ScaleSphereEmitterOnBlack: the emitting ball grows about its centre."""
    sc = scene(light=shape("light", ball([0.0, 0.0, 0.0], 0.7), radiance=1.0))
    update = scale_vertices(mi.traverse(sc), "light.vertex_positions")
    assert_agrees(fd_agreement(sc, update, 2, 64, 0.003, 1024))


def test_translate_constant_lit_rectangle():
    """TranslateDiffuseRectangleConstant (turned 30°): a diffuse square against a uniform sky."""
    sc = scene(rectangle=shape("rectangle", tilted_rectangle()), sky={"type": "constant"})
    update = translate_vertices(mi.traverse(sc), ["rectangle.vertex_positions"], (1, 0, 0))
    assert_agrees(fd_agreement(sc, update, 2, 64, 0.003, 1024))


def test_translate_plane_under_envmap():
    """TranslatePlaneUnderEnvmap with the plane small enough to be seen whole: it moves towards
    the camera under a procedural sky, and its outline grows in the image."""
    sc = scene(plane=shape("plane", tilted_rectangle()), sky={"type": "envmap", "bitmap": sky()})
    update = translate_vertices(mi.traverse(sc), ["plane.vertex_positions"], (0, 0, 1))
    assert_agrees(fd_agreement(sc, update, 2, 64, 0.003, 1024))


def test_translate_camera():
    """TranslateCamera (commented out in Mitsuba's own list): the camera moves sideways in its own
    frame over a ball under a uniform sky."""
    sc = scene(ball=shape("ball", ball([0.0, 0.0, 0.0], 1.0, 3)), sky={"type": "constant"})
    update = translate_sensor(mi.traverse(sc), "sensor.to_world", (1, 0, 0))
    assert_agrees(fd_agreement(sc, update, 2, 64, 0.003, 1024))


def test_analytic_sphere_emitter_is_named_not_silently_zero():
    """The plugin differentiates triangle meshes only: a moving ``sphere`` shape (Mitsuba's own
    emitter test uses one in its disk/sphere variants) gets a warning that names it."""
    sc = scene(light={"type": "sphere", "center": [0.1, 0, 0], "radius": 0.7,
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}})
    params = mi.traverse(sc)
    initial = mi.Transform4f(params["light.to_world"])
    theta = mi.Float(0.0)
    dr.enable_grad(theta)
    params["light.to_world"] = mi.Transform4f().translate(mi.Vector3f(theta, 0, 0)) @ initial
    params.update()
    dr.forward(theta, dr.ADFlag.ClearEdges)
    with pytest.warns(UserWarning, match="'light'.*cannot differentiate"):
        psdr_integrator(2).render_forward(sc, params=theta, spp=4, seed=0)
