"""The psdr estimator as a Mitsuba integrator plugin (``type: psdr``).

After :func:`register`, ``mi.render(scene, params, integrator=mi.load_dict({'type': 'psdr'}))``
returns our interior render, and ``dr.forward`` / ``dr.backward`` through it use all four terms
(interior, primary, direct, indirect). Boundary terms cover every mesh whose
``vertex_positions`` have gradients enabled, like Mitsuba's projective integrators.

Properties: ``max_depth`` (3), ``primary_spp`` and ``boundary_spp`` (default: the render's spp),
``sampling`` (``mis``), ``terms`` (comma-separated, default all four), ``passes`` (1).
"""
from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import drjit as dr
import mitsuba as mi

from ..config.estimator_section import EstimatorConfig
from ..config.vocabularies import TERMS
from ..estimators.boundary_sampling import BoundaryEdges
from .estimate import Settings, ad_image, term_passes
from .plugin import differentiable_meshes
from .render import render_view


@dataclass
class SceneView:
    """What the estimators need from a scene, for any ``mi.Scene`` and one sensor."""
    mi_scene: mi.Scene
    sensors: list
    resolution: tuple
    objects: dict
    config: object


class PsdrRenderer:
    """What the ``psdr`` integrator does, for any ``mi.Scene``: its properties (``max_depth``,
    ``primary_spp``, ``boundary_spp``, ``sampling``, ``passes``, ``terms``) and the primal render,
    the forward and the backward pass, each a sum of :func:`psdr_cli.rendering.estimate.ad_image` passes."""

    def __init__(self, props):
        self.max_depth = props.get("max_depth", 3)
        self.primary_spp = props.get("primary_spp", 0)
        self.boundary_spp = props.get("boundary_spp", 0)
        self.sampling = props.get("sampling", "mis")
        self.passes = props.get("passes", 1)
        self.terms = tuple(t.strip() for t in props.get("terms", ",".join(TERMS)).split(","))
        unknown = [t for t in self.terms if t not in TERMS]
        if unknown:
            raise ValueError(f"psdr integrator: unknown term '{unknown[0]}' (expected some of {', '.join(TERMS)})")

    def settings(self, spp: int, seed: int) -> Settings:
        estimator = EstimatorConfig(spp=spp, primary_spp=self.primary_spp or spp,
                                    boundary_spp=self.boundary_spp or spp, sampling=self.sampling,
                                    passes=self.passes)
        return Settings(estimator, max_depth=self.max_depth, seed=int(seed))

    def view(self, scene, params, sensor) -> tuple:
        size = tuple(int(s) for s in sensor.film().size())
        # params may be SceneParameters, a reduced set (params.keep) or θ itself: read the shapes
        objects = differentiable_meshes(scene, sensor) if params is not None else {}
        sv = SceneView(scene, [sensor], size, objects, SimpleNamespace(max_depth=self.max_depth, hide_background=False))
        return sv, BoundaryEdges.from_scene(sv)

    @staticmethod
    def spp_of(sensor, spp):
        return spp if spp else sensor.sampler().sample_count()

    def render(self, scene, sensor, seed, spp):
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        spp = self.spp_of(sensor, spp)
        sv, _ = self.view(scene, None, sensor)
        with dr.suspend_grad():
            image = render_view(sv, 0, spp, seed=int(seed), max_depth=self.max_depth)
        return mi.TensorXf(image)

    def pass_images(self, scene, params, sensor, seed, spp):
        """Yield the AD image of each pass (flat W·H·3), weighted so that they sum to the estimate."""
        sv, edges = self.view(scene, params, sensor)
        settings = self.settings(self.spp_of(sensor, spp), seed)
        pixels = sv.resolution[0] * sv.resolution[1]
        n = max(len(term_passes(t, settings, pixels)) for t in self.terms)
        for p in range(n):
            yield ad_image(sv, edges, 0, self.terms, settings, p, scale=1.0 / n)

    def render_forward(self, scene, params, sensor, seed, spp):
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        with dr.resume_grad():
            total = None
            for img in self.pass_images(scene, params, sensor, seed, spp):
                total = img if total is None else total + img
            dr.forward_to(total)
            grad = dr.grad(total)
        W, H = (int(s) for s in sensor.film().size())
        return mi.TensorXf(dr.detach(grad), (H, W, 3))

    def render_backward(self, scene, params, grad_in, sensor, seed, spp):
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        weights = dr.detach(mi.Float(dr.ravel(grad_in)))
        with dr.resume_grad():
            for img in self.pass_images(scene, params, sensor, seed, spp):
                dr.backward(dr.sum(img * weights))

    def describe(self) -> str:
        return f"PsdrIntegrator[terms={','.join(self.terms)}, sampling={self.sampling}, max_depth={self.max_depth}]"


_CLASSES = {}


def integrator_class():
    """The integrator class for the active variant (Mitsuba base classes exist only after
    ``mi.set_variant``): Mitsuba's entry points, each handed to a :class:`PsdrRenderer`."""
    if mi.variant() in _CLASSES:
        return _CLASSES[mi.variant()]

    class PsdrIntegrator(mi.CppADIntegrator):
        """Mitsuba-facing wrapper of :func:`psdr_cli.rendering.estimate.ad_image` (:class:`PsdrRenderer`)."""

        def __init__(self, props=None):
            props = mi.Properties() if props is None else props
            super().__init__(props)
            self.psdr = PsdrRenderer(props)

        def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
            return self.psdr.render(scene, sensor, seed, spp)

        def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
            return self.psdr.render_forward(scene, params, sensor, seed, spp)

        def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
            self.psdr.render_backward(scene, params, grad_in, sensor, seed, spp)

        def to_string(self):
            return self.psdr.describe()

    _CLASSES[mi.variant()] = PsdrIntegrator
    return PsdrIntegrator


def register():
    """Register the ``psdr`` integrator with Mitsuba (call after choosing a variant)."""
    cls = integrator_class()
    mi.register_integrator("psdr", lambda props: cls(props))
