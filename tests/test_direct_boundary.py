"""Direct boundary term against finite differences of the forward render (shadow of a moving
occluder under an area light), technique agreement, and reverse mode against forward mode."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from psdr_cli.api import setup
from psdr_cli.estimators.boundary_sampling import BoundaryEdges
from psdr_cli.estimators.direct import direct_boundary
from psdr_cli.estimators.passes import make_sampler
from psdr_cli.experiment.load import parse_experiment
from psdr_cli.rendering.render import render_view
from psdr_cli.scene.build import build_scene

R = 32
SEEDS = 8
KEY = "occ.vertex_positions"
SHADOW = {
    "name": "shadow",
    "scene": {
        "film": {"width": R, "height": R}, "max_depth": 2,
        "cameras": [{"origin": [0, -2.2, 2.2], "target": [0, 0, 0.2], "fov": 40}],
        "emitters": [{"type": "area", "center": [0.4, 0.9, 2.0], "normal": [0, 0, -1], "size": [0.6, 0.6],
                      "radiance": 20}],
        "objects": [{"name": "occ", "mesh": {"shape": "sphere", "radius": 0.3, "subdivisions": 2},
                     "transform": {"translate": [0, 0, 0.6]},
                     "bsdf": {"type": "diffuse", "reflectance": [0.7, 0.5, 0.3]}},
                    {"name": "floor", "mesh": {"shape": "plane", "size": 4},
                     "bsdf": {"type": "diffuse", "reflectance": 0.8}, "edges": False}]}}


class Shadow:
    """The scene with θ = x-translation of the occluder's vertices."""

    def __init__(self, tmp_path):
        exp = parse_experiment(SHADOW, tmp_path / "shadow.yaml", cwd=tmp_path)
        setup(exp)
        self.scene = build_scene(exp)
        self.params = mi.traverse(self.scene.mi_scene)
        self.V0 = mi.Float(self.params[KEY])
        self.edges = BoundaryEdges.from_scene(self.scene)

    def set_theta(self, theta):
        self.params[KEY] = dr.ravel(dr.unravel(mi.Point3f, self.V0) + theta * mi.Vector3f(1, 0, 0))
        self.params.update()

    def boundary(self, technique, seed, n):
        theta = mi.Float(0.0)
        dr.enable_grad(theta)
        self.set_theta(theta)
        img = direct_boundary(self.scene.mi_scene, self.scene.sensors[0], self.edges, self.params[KEY], n,
                              make_sampler(seed, n), technique=technique)
        dr.set_grad(theta, 1.0)
        dr.forward_to(img)
        grad = np.array(dr.grad(img)).reshape(R, R, 3)
        self.set_theta(mi.Float(0.0))
        return grad

    def finite_difference(self, h, seed, spp):
        """Central difference with common random numbers (same seed on both sides)."""
        imgs = []
        for s in (1.0, -1.0):
            self.set_theta(mi.Float(s * h))
            imgs.append(render_view(self.scene, 0, spp, seed=seed))
        self.set_theta(mi.Float(0.0))
        return (imgs[0] - imgs[1]) / (2 * h)

    def floor_mask(self, h):
        """Pixels whose footprint never sees the occluder for θ ∈ {−h, 0, h}, dilated by 2 pixels
        (there only the shadow boundary changes the image)."""
        sensor, n = self.scene.sensors[0], 8
        occ = mi.ShapePtr([s for s in self.scene.mi_scene.shapes() if s.id() == "occ"][0])
        idx = dr.arange(mi.UInt32, R * R * n * n)
        pix, sub = idx // (n * n), idx % (n * n)
        pos = mi.Point2f(mi.Float(pix % R) + (mi.Float(sub % n) + 0.5) / n,
                         mi.Float(pix // R) + (mi.Float(sub // n) + 0.5) / n)
        ray, _ = sensor.sample_ray(0.0, 0.0, pos / R, mi.Point2f(0.5))
        covered = np.zeros((R, R), bool)
        for theta in (-h, 0.0, h):
            self.set_theta(mi.Float(theta))
            hit = np.array(self.scene.mi_scene.ray_intersect(ray).shape == occ)
            covered |= hit.reshape(R * R, n * n).any(axis=1).reshape(R, R)
        self.set_theta(mi.Float(0.0))
        return ~binary_dilation(covered, iterations=2)


@pytest.fixture(scope="module")
def shadow(tmp_path_factory):
    return Shadow(tmp_path_factory.mktemp("shadow"))


@pytest.fixture(scope="module")
def fd_halves(shadow):
    """Per-seed masked sums of the FD image over the left and right image halves."""
    mask = shadow.floor_mask(0.01)
    fd = np.stack([shadow.finite_difference(0.01, 30 + s, 4096) for s in range(SEEDS)])
    return halves(fd, mask), mask


def halves(images, mask):
    m = images * mask[None, :, :, None]
    return np.stack([m[:, :, : R // 2].sum(axis=(1, 2, 3)), m[:, :, R // 2:].sum(axis=(1, 2, 3))], axis=1)


def test_edges_of_the_occluder_only(shadow):
    assert shadow.edges.names == ["occ"] and shadow.edges.count == 480  # icosphere(2): 480 edges, all convex


@pytest.mark.parametrize("technique", ["light", "dir", "mis"])
def test_direct_boundary_matches_finite_differences(shadow, fd_halves, technique):
    fd, mask = fd_halves
    bd = halves(np.stack([shadow.boundary(technique, 200 + s, 1 << 20) for s in range(SEEDS)]), mask)
    diff = bd.mean(0) - fd.mean(0)
    se = np.sqrt(bd.var(0, ddof=1) / SEEDS + fd.var(0, ddof=1) / SEEDS)
    assert np.all(np.abs(fd.mean(0)) > 20 * se), "the shadow signal must stand well above the noise"
    assert np.all(np.abs(diff) < 3 * se), (technique, bd.mean(0), fd.mean(0), se)


def test_wrong_sign_would_be_caught(shadow, fd_halves):
    """The check above can fail: a mirrored edge orientation (σ → −σ) flips every value."""
    fd, mask = fd_halves
    bd = -halves(shadow.boundary("mis", 7, 1 << 20)[None], mask)[0]
    assert np.all(np.abs(bd - fd.mean(0)) > 50 * fd.std(0, ddof=1) / np.sqrt(SEEDS))


def test_reverse_mode_matches_forward_mode(shadow):
    """Σ_v ∂L/∂x_v (reverse) equals dL/dθ (forward) for L = Σ w·image with θ moving all vertices in x."""
    weights = mi.Float(np.random.default_rng(0).normal(size=R * R * 3).astype(np.float32))
    n, seed = 1 << 18, 5
    # forward
    theta = mi.Float(0.0)
    dr.enable_grad(theta)
    shadow.set_theta(theta)
    img = direct_boundary(shadow.scene.mi_scene, shadow.scene.sensors[0], shadow.edges, shadow.params[KEY], n,
                          make_sampler(seed, n), technique="mis")
    loss = dr.sum(img * weights)
    dr.set_grad(theta, 1.0)
    dr.forward_to(loss)
    forward = dr.grad(loss)[0]
    # reverse
    P = mi.Float(shadow.V0)
    dr.enable_grad(P)
    shadow.params[KEY] = P
    shadow.params.update()
    img = direct_boundary(shadow.scene.mi_scene, shadow.scene.sensors[0], shadow.edges, shadow.params[KEY], n,
                          make_sampler(seed, n), technique="mis")
    dr.backward(dr.sum(img * weights))
    reverse = float(np.array(dr.grad(P)).reshape(-1, 3)[:, 0].sum())
    shadow.set_theta(mi.Float(0.0))
    assert abs(forward) > 1e-3
    assert reverse == pytest.approx(forward, rel=1e-3)
