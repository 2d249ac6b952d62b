"""Held-out cameras aligned to a recovered scene before they are scored (``psdr evaluate`` of a
run that refined its cameras: ``optimize.cameras``).

A held-out photograph's pose is as wrong as the training views' were, and scoring a
reconstruction through a wrong pose measures the pose, not the reconstruction. With the
recovered scene fixed, each held-out view's pose correction (r, τ) of
:mod:`psdr_cli.optimisation.camera_refinement` (no gauge: the fixed scene pins every pose) is fitted alone to
its photograph T by Adam on

    L_v = mean |I_v(r_v, τ_v) − T_v|,

I_v psdr's estimate of the experiment's terms (the camera derivatives of the interior, primary
and direct terms) at :data:`SPP` samples per pixel, for :data:`ITERATIONS` steps of :data:`RATE`
(radians and camera distances) after a short ramp, falling linearly to a tenth of it. Views
whose fit runs away stop where they were, as in the loop.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config.unknowns import CamerasUnknown
from ..estimators.boundary_sampling import edge_list
from ..optimisation.camera_refinement import CameraCorrections
from ..rendering.camera_motion import with_all_edges
from ..rendering.estimate import Settings, ad_image
from ..support.jitarray import jit_array

#: Adam steps of a held-out view's pose fit (the orbit about the object, seen only through
#: parallax, is the slowest part; docs/optimize.md, "Camera poses").
ITERATIONS = 100

#: Adam's step at the start of the fit (radians, camera distances).
RATE = 2e-3

#: Samples per pixel of the interior term in the fit (at least; its gradients drive the pose).
SPP = 32


def align_views(scene, exp, targets: list, iterations: int | None = None, warn=None) -> CameraCorrections:
    """Fit every view of ``scene`` (the held-out cameras of ``exp``) to its target image
    (flat-able (H, W, 3) linear arrays, as the loop fits them) for ``iterations`` steps (default
    :data:`ITERATIONS`); the scene is left with the aligned cameras written (no AD). Returns the
    corrections found."""
    iterations = ITERATIONS if iterations is None else iterations
    with_all_edges(scene)
    settings = Settings.from_experiment(exp, spp=max(exp.estimator.spp, SPP))
    params = mi.traverse(scene.mi_scene)
    cfg = CamerasUnknown(mode="on", learning_rate=RATE, learning_rate_final=RATE / 10, start=0, warmup=5)
    cams = CameraCorrections(cfg, params, len(scene.sensors), {}, gauge=False)
    goal = [jit_array(mi.Float, np.ravel(t)) for t in targets]
    with dr.suspend_grad():  # the mesh is fixed: one edge table for every step
        edges = edge_list(scene, exp.estimator, settings.edge_sort)
    for it in range(iterations):
        cams.attached = True
        cams.write(params)
        params.update()
        loss = mi.Float(0.0)
        for v, target in enumerate(goal):
            image = ad_image(scene, edges, v, exp.estimator.terms, settings, pass_index=it)
            loss += dr.mean(dr.abs(image - target))
        dr.backward(loss)
        cams.step(it, iterations, warn or (lambda line: None))
    cams.detach(params)
    params.update()
    return cams
