"""Cameras with a focal length and an off-centre principal point: Mitsuba's convention
(``principal_point_offset_x/y``), ``scene.cameras[].principal_point``, :func:`pinhole_camera`
from OpenCV poses and intrinsics, psdr's film projection and camera connections with an offset,
and ``psdr grad --fd`` through such a camera."""
import json
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import yaml

from conftest import experiment, run_cli
from psdr_cli.config.cameras_section import CameraConfig
from psdr_cli.errors import ConfigError
from psdr_cli.estimators.camera import LaneCameras, Projection, SensorCamera, camera_connection
from psdr_cli.experiment.load import parse_experiment
from psdr_cli.run_folder.fingerprint import run_fingerprint
from psdr_cli.run_folder.fingerprint_v1 import fingerprint_v1
from psdr_cli.scene.build import sensor_dict
from psdr_cli.scene.pinhole import pinhole_camera
from psdr_cli.support import backend
from psdr_cli.support.verdict import agrees, describe
from psdr_cli.target_sources.rendered_mesh import target_key


@pytest.fixture(scope="module", autouse=True)
def variant():
    backend.select_variant()  # auto: llvm_ad_rgb here, PSDR_VARIANT if set


def parse(d, tmp_path):
    return parse_experiment(d, tmp_path / "exp.yaml", cwd=tmp_path, warn=lambda m: None)


def sensor(cam, width, height):
    return mi.load_dict(sensor_dict(cam, width, height))


def project(s, X):
    """Mitsuba's film position (pixels) of world points X (n, 3) and whether it is on the film."""
    it = dr.zeros(mi.Interaction3f)
    it.p = mi.Point3f(*(mi.Float(np.ascontiguousarray(X[:, i], np.float32)) for i in range(3)))
    ds, _ = s.sample_direction(it, mi.Point2f(0.5))
    return np.stack([np.asarray(ds.uv.x, float), np.asarray(ds.uv.y, float)], 1), np.asarray(ds.pdf) > 0


def test_mitsuba_principal_point_convention():
    """Mitsuba 3.9 (perspective.cpp): ds.uv = (screen − offset)·resolution, and sample_ray adds
    the offset to the film sample. So the optical axis lands on pixel (W(½ − ox), H(½ − oy)):
    offsets are fractions of the film, and a positive one moves the principal point left / up."""
    W, H = 40, 30
    for ox, oy in [(0.0, 0.0), (0.25, 0.0), (0.0, 0.25), (0.12, -0.08)]:
        cam = CameraConfig(origin=(0.0, 0.0, 0.0), target=(0.0, 1.0, 0.0), fov=50.0, principal_point=(ox, oy))
        s = sensor(cam, W, H)
        uv, on = project(s, np.array([[0.0, 3.0, 0.0]]))
        assert on[0] and np.allclose(uv[0], [W * (0.5 - ox), H * (0.5 - oy)], atol=1e-4), (ox, oy, uv)
        ray, _ = s.sample_ray(0.0, 0.5, mi.Point2f(0.5 - ox, 0.5 - oy), mi.Point2f(0.5))
        assert np.allclose(np.ravel(ray.d), [0, 1, 0], atol=1e-6)
    assert "principal_point_offset_x" not in sensor_dict(CameraConfig((0, 0, 0), (0, 1, 0)), W, H)


def random_rotation(rng):
    Q, R = np.linalg.qr(rng.normal(size=(3, 3)))
    Q = Q * np.sign(np.diag(R))
    return Q if np.linalg.det(Q) > 0 else -Q


def test_pinhole_camera_matches_opencv_projection():
    """For random rigid cameras (OpenCV axes) and intrinsics, Mitsuba's sensor from
    sensor_dict(pinhole_camera(...)) puts random world points on the pixel K[R|t]X gives (pixel
    corners at integers, as cx, cy) within 1e-3 px, and the camera ray through that pixel points
    at the world point."""
    rng = np.random.default_rng(7)
    worst_px, worst_ray = 0.0, 0.0
    for _ in range(12):
        W, H = int(rng.integers(48, 640)), int(rng.integers(48, 480))
        fx = W / (2 * math.tan(math.radians(rng.uniform(20, 100)) / 2))
        cx, cy = W * rng.uniform(0.3, 0.7), H * rng.uniform(0.3, 0.7)
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = random_rotation(rng), rng.uniform(-2, 2, 3)
        s = sensor(pinhole_camera(M, fx, fx, cx, cy, W, H), W, H)
        # world points: random pixels and depths through the inverse OpenCV model
        n = 256
        pix = rng.uniform([0.5, 0.5], [W - 0.5, H - 0.5], (n, 2))
        z = rng.uniform(1, 8, n)
        Xc = np.stack([(pix[:, 0] - cx) / fx * z, (pix[:, 1] - cy) / fx * z, z], 1)
        X = Xc @ M[:3, :3].T + M[:3, 3]
        # OpenCV: x = K [R_cw | t_cw] X with R_cw = Rᵀ, t_cw = −Rᵀ t
        K = np.array([[fx, 0, cx], [0, fx, cy], [0, 0, 1]])
        R_cw = M[:3, :3].T
        x = (K @ (R_cw @ X.T - (R_cw @ M[:3, 3])[:, None])).T
        cv = x[:, :2] / x[:, 2:]
        uv, on = project(s, X)
        assert on.all()
        worst_px = max(worst_px, np.abs(uv - cv).max())
        ray, _ = s.sample_ray(0.0, 0.5, mi.Point2f(*(mi.Float(cv[:, i] / (W, H)[i]) for i in range(2))), mi.Point2f(0.5))
        d = np.stack([np.asarray(c, float) for c in (ray.d.x, ray.d.y, ray.d.z)], 1)
        to_x = X - M[:3, 3]
        to_x /= np.linalg.norm(to_x, axis=1, keepdims=True)
        worst_ray = max(worst_ray, (np.linalg.norm(np.cross(d, to_x), axis=1) * fx).max())  # angle in pixels
    assert worst_px < 1e-3 and worst_ray < 1e-3, (worst_px, worst_ray)


def test_pinhole_camera_refusals():
    M = np.eye(4)
    cam = pinhole_camera(M, 100.0, 100.4, 40.0, 30.0, 80, 60)  # |fx/fy − 1| = 0.004: accepted
    assert cam.principal_point == (0.0, 0.0) and cam.up == (-0.0, -1.0, -0.0) and cam.target == (0.0, 0.0, 1.0)
    assert math.isclose(cam.fov, math.degrees(2 * math.atan(80 / 200)))
    with pytest.raises(ValueError, match="square"):
        pinhole_camera(M, 100.0, 100.6, 40.0, 30.0, 80, 60)
    mirror = np.diag([1.0, -1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="rotation"):
        pinhole_camera(mirror, 100.0, 100.0, 40.0, 30.0, 80, 60)
    with pytest.raises(ValueError, match="principal point"):
        pinhole_camera(M, 100.0, 100.0, 400.0, 30.0, 80, 60)


def test_principal_point_key(tmp_path):
    """``principal_point: [ox, oy]`` parses into the camera; bad values are one line naming the
    key; at its default it changes no fingerprint and no target key."""
    d = experiment(optimize={"object": "ball"})
    base = parse(d, tmp_path)
    d["scene"]["cameras"][0]["principal_point"] = [0, 0]
    zero = parse(d, tmp_path)
    assert zero.scene.cameras[0].principal_point == (0.0, 0.0)
    ref = (np.zeros((3, 3)), np.zeros((1, 3), int))
    same = (run_fingerprint(zero), fingerprint_v1(zero), target_key(zero, ref, 4))
    assert same == (run_fingerprint(base), fingerprint_v1(base), target_key(base, ref, 4))
    d["scene"]["cameras"][0]["principal_point"] = [0.12, -0.08]
    off = parse(d, tmp_path)
    assert off.scene.cameras[0].principal_point == (0.12, -0.08)
    assert run_fingerprint(off) != same[0] and target_key(off, ref, 4) != same[2]
    for bad, words in [([0.1], "expected [ox, oy]"), ("centre", "expected [ox, oy]"), ([0.1, True], "expected [ox, oy]"),
                       ([12, -8], "within ±1 (fractions of the film width and height, not pixels)"),
                       ([float("nan"), 0], "finite")]:
        d["scene"]["cameras"][0]["principal_point"] = bad
        with pytest.raises(ConfigError) as info:
            parse(d, tmp_path)
        msg = str(info.value)
        assert msg.startswith(f"{tmp_path / 'exp.yaml'}: scene.cameras[0].principal_point: ") and words in msg, msg
        assert "\n" not in msg


def test_projection_and_importance_with_an_offset():
    """psdr's Projection is Mitsuba's sample_direction uv with an offset; camera_connection's
    importance is the pinhole's also where Mitsuba 3.9 returns 0 (outside the centred rectangle)."""
    W, H = 40, 30
    cam = CameraConfig(origin=(0.3, -2.5, 1.0), target=(0.0, 0.0, 0.3), fov=37.0, principal_point=(0.12, -0.08))
    s = sensor(cam, W, H)
    rng = np.random.default_rng(3)
    X = np.c_[rng.uniform(-3, 3, (2000, 2)), np.zeros(2000)]  # on the floor below
    uv, on = project(s, X)
    p = mi.Point3f(*(mi.Float(np.ascontiguousarray(X[:, i], np.float32)) for i in range(3)))
    q, _ = Projection(s)(p)
    assert np.abs(np.stack([np.asarray(q.x), np.asarray(q.y)], 1) - uv)[on].max() < 1e-3
    floor = {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([10, 10, 1])}
    scene = mi.load_dict({"type": "scene", "cam": sensor_dict(cam, W, H), "floor": floor})
    imp, _, _, _, ok = camera_connection(scene, SensorCamera(s, W, H), p, True)
    imp, ok = np.asarray(imp[0]), np.asarray(ok)
    # W_e = 1 / (A cos³θ d²), A = (2 tan(f/2))² H/W the film's area at distance 1
    v = X - cam.origin
    axis = np.subtract(cam.target, cam.origin) / np.linalg.norm(np.subtract(cam.target, cam.origin))
    d2 = (v * v).sum(1)
    cos = v @ axis / np.sqrt(d2)
    expected = 1 / ((2 * math.tan(math.radians(cam.fov) / 2)) ** 2 * H / W * cos ** 3 * d2)
    assert (ok == on).all() and on.sum() > 300
    assert np.allclose(imp[ok], expected[ok], rtol=1e-4), np.abs(imp[ok] / expected[ok] - 1).max()
    it = dr.zeros(mi.Interaction3f)
    it.p = p
    _, mitsuba = s.sample_direction(it, mi.Point2f(0.5))
    assert (np.asarray(mitsuba[0])[ok] == 0).sum() > 20  # the strip Mitsuba's own importance misses
    # the same camera gathered per lane (a batch's lanes, issue 38): the same connection
    other = sensor(CameraConfig(origin=(2.0, 1.0, 3.0), target=(0.0, 0.0, 0.0), fov=50.0), W, H)
    lanes = LaneCameras([other, s], mi.UInt32(np.ones(len(X), np.uint32)), W, H)
    imp_l, d0_l, uv_l, _, ok_l = camera_connection(scene, lanes, p, True)
    _, d0, uv_s, _, _ = camera_connection(scene, SensorCamera(s, W, H), p, True)
    assert (np.asarray(ok_l) == ok).all()
    assert np.allclose(np.asarray(imp_l[0])[ok], imp[ok], rtol=1e-4)
    assert np.abs(np.asarray(d0_l) - np.asarray(d0))[:, ok].max() < 1e-5
    assert np.abs(np.asarray(uv_l) - np.asarray(uv_s))[:, ok].max() < 1e-3


def test_projection_takes_any_vector_type_as_a_point():
    """The boundary terms hand the projection points typed as Point3f or as Vector3f (x^B − ω is
    a vector to Dr.Jit): both are points, moved by the camera's translation."""
    cam = CameraConfig(origin=(0.3, -2.5, 1.0), target=(0.0, 0.0, 0.3), fov=37.0, principal_point=(0.12, -0.08))
    proj = Projection(sensor(cam, 40, 30))
    X = [mi.Float([0.1, -0.4, 0.3]), mi.Float([0.2, 0.0, -0.3]), mi.Float([0.0, 0.5, 0.2])]
    for f in (proj.importance, lambda x: proj(x)[0].x, lambda x: proj(x)[1]):
        assert np.allclose(np.asarray(f(mi.Vector3f(*X))), np.asarray(f(mi.Point3f(*X))), rtol=1e-6)


def test_grad_matches_finite_differences_through_an_off_centre_camera(tmp_path):
    """``psdr grad --fd`` through a camera made by :func:`pinhole_camera` (fx = 60 px on a 32×24
    film: fov 29.9°, principal point (0.38 W, 0.58 H): offset (0.12, −0.08)): a dark ball moving
    in front of a constant background, whose gradient is its silhouette (the primary term). With
    the offset dropped from the film projection, the primary term's camera rays miss their edges
    and the estimate is 0 (max |z| 159 over the signal tiles, mean z² 2.7e3)."""
    W, H = 32, 24
    forward = np.array([0.0, 1.0, -0.15]) / math.hypot(1.0, 0.15)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = right, np.cross(forward, right), forward, [0.15, -3.0, 0.9]
    cam = pinhole_camera(M, 60.0, 60.0, 0.38 * W, 0.58 * H, W, H)
    assert np.allclose(cam.principal_point, (0.12, -0.08)) and abs(cam.fov - 29.86) < 0.01
    data = {"name": "offcentre", "seed": 4,
            "scene": {"film": {"width": W, "height": H}, "max_depth": 1,
                      "cameras": [{"origin": list(cam.origin), "target": list(cam.target), "up": list(cam.up),
                                   "fov": cam.fov, "principal_point": list(cam.principal_point)}],
                      "emitters": [{"type": "constant", "radiance": [1.0, 0.8, 0.6]}],
                      "objects": [{"name": "ball", "mesh": {"shape": "sphere", "radius": 0.35, "subdivisions": 2},
                                   "transform": {"translate": [0.0, 0.0, 0.45]}, "smooth": True,
                                   "bsdf": {"type": "diffuse", "reflectance": 0.5}}]},
            "parameter": {"object": "ball", "kind": "translate", "axis": [1, 0, 0.5]},
            "estimator": {"terms": ["primary"]}}
    cfg = tmp_path / "offcentre.yaml"
    cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    proc = run_cli("grad", cfg, "--fd", 0.005, "--spp", 64, "--fd-spp", 16384, "--out", tmp_path)
    assert proc.returncode == 0, proc.stderr
    stats = json.loads((tmp_path / "offcentre" / "grad" / "summary.json").read_text())["views"][0]["fd_agreement"]
    assert agrees(stats), describe(stats)


def test_xml_sensor_keeps_its_principal_point(tmp_path):
    """An XML ``perspective`` sensor with ``principal_point_offset_x/y`` is read (no longer
    refused): its camera carries the offset and the rebuilt sensor projects as the XML's."""
    from psdr_cli import api
    from psdr_cli.scene.build import build_scene
    from test_mitsuba_scene import XML, write_twins
    xml_cfg, _ = write_twins(tmp_path)
    text = (tmp_path / "scene.xml").read_text()
    assert XML.count('<string name="fov_axis" value="x"/>') == 1
    (tmp_path / "scene.xml").write_text(text.replace(
        '<string name="fov_axis" value="x"/>', '<string name="fov_axis" value="x"/>'
        '<float name="principal_point_offset_x" value="0.1"/><float name="principal_point_offset_y" value="-0.05"/>'))
    exp = api.load_experiment(xml_cfg, warn=lambda m: None)
    assert np.allclose(exp.scene.cameras[0].principal_point, (0.1, -0.05))
    s = build_scene(exp).sensors[0]
    uv, on = project(s, np.array([[0.0, 0.0, 0.3]]))   # the XML camera's target: on the optical axis
    assert on[0] and np.allclose(uv[0], [24 * 0.4, 16 * 0.55], atol=1e-3)
