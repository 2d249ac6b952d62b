"""Reverse mode and the Mitsuba plugin: agreement with Mitsuba's prb_projective, and a tiny
vertex optimisation that lowers an image loss."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from conftest import REPO
from psdr_cli.api import setup
from psdr_cli.config.estimator_section import EstimatorConfig
from psdr_cli.config.vocabularies import TERMS
from psdr_cli.estimators.boundary_sampling import BoundaryEdges
from psdr_cli.experiment.load import load_experiment
from psdr_cli.geometry.parameters import Parameter
from psdr_cli.rendering.estimate import Settings, ad_image, forward_gradient
from psdr_cli.rendering.reference import block_sums, mean_and_error, mitsuba_projective
from psdr_cli.scene.build import build_scene

SILHOUETTE = REPO / "configs" / "validation" / "silhouette.yaml"


@pytest.fixture(scope="module")
def silhouette():
    exp = load_experiment(SILHOUETTE)
    setup(exp)
    scene = build_scene(exp)
    return exp, scene, Parameter(scene, exp.parameter), BoundaryEdges.from_scene(scene)


def test_total_gradient_matches_mitsuba_prb_projective(silhouette):
    """A smooth sphere's silhouette (Mitsuba needs smooth shading): tile sums agree with Mitsuba's
    independent projective estimator within Monte Carlo error."""
    exp, scene, parameter, edges = silhouette
    mi.set_log_level(mi.LogLevel.Error)
    settings = Settings(EstimatorConfig(spp=16, primary_spp=512, boundary_spp=16), max_depth=exp.scene.max_depth, seed=7)
    ours = forward_gradient(scene, edges, parameter, 0, "primary", settings, min_passes=8)
    e, e_se = mean_and_error(block_sums(ours.passes, 8), ours.weights)
    theirs = mitsuba_projective(scene, parameter, 0, 256, seed=3, batches=8)
    m, m_se = mean_and_error(block_sums(theirs, 8))
    z = (e - m) / np.sqrt(e_se ** 2 + m_se ** 2 + 1e-30)
    signal = np.abs(m) > 5 * m_se
    assert signal.sum() >= 6
    assert np.all(np.abs(z[signal]) < 4), z
    assert abs(e.sum() - m.sum()) < 3 * np.sqrt((e_se ** 2).sum() + (m_se ** 2).sum())


def test_plugin_forward_and_reverse_agree(silhouette):
    """mi.render with the registered 'psdr' integrator: dr.forward (θ = x-translation) equals the
    x-components of dr.backward summed over vertices."""
    from psdr_cli.rendering.integrator import register
    exp, scene, parameter, _ = silhouette
    register()
    integrator = mi.load_dict({"type": "psdr", "max_depth": exp.scene.max_depth})
    theta = mi.Float(0.0)
    dr.enable_grad(theta)
    parameter.apply(theta)
    dr.set_grad(theta, 1.0)
    dr.forward_from(theta, dr.ADFlag.ClearEdges)
    img = mi.render(scene.mi_scene, parameter.params, integrator=integrator, spp=64, seed=5)
    dr.forward_to(img)
    forward = float(np.asarray(dr.grad(img)).sum())
    parameter.reset()
    P = parameter.params["ball.vertex_positions"]
    dr.enable_grad(P)
    parameter.params.update()
    img = mi.render(scene.mi_scene, parameter.params, integrator=integrator, spp=64, seed=5)
    dr.backward(dr.sum(img))
    reverse = float(np.asarray(dr.grad(P)).reshape(-1, 3)[:, 0].sum())
    parameter.reset()
    assert abs(forward) > 1.0 and reverse == pytest.approx(forward, rel=1e-3)


def test_reverse_mode_vertex_optimisation_lowers_the_loss(silhouette):
    """Vertices of the sphere start 0.12 to the left of the target's; 25 Adam steps on the L1
    image loss (reverse mode through all terms) cut the loss at least in half."""
    exp, scene, parameter, edges = silhouette
    key = "ball.vertex_positions"
    params = parameter.params
    V0 = mi.Float(params[key])
    settings = Settings(EstimatorConfig(spp=4, primary_spp=16, boundary_spp=4), max_depth=exp.scene.max_depth)
    params[key] = dr.ravel(dr.unravel(mi.Point3f, V0) + mi.Vector3f(0.12, 0, 0))
    params.update()
    with dr.suspend_grad():
        target = ad_image(scene, edges, 0, ("interior",), Settings(EstimatorConfig(spp=256), max_depth=1), pass_index=99)
    params[key] = mi.Float(V0)
    params.update()
    opt = mi.ad.Adam(lr=0.01)
    opt[key] = params[key]
    losses = []
    for it in range(25):
        params.update(opt)
        settings.seed = it
        img = ad_image(scene, edges, 0, TERMS, settings)
        loss = dr.mean(dr.abs(img - target))
        dr.backward(loss)
        losses.append(float(loss[0]))
        opt.step()
    params[key] = V0
    params.update()
    assert np.mean(losses[-5:]) < 0.5 * np.mean(losses[:3]), losses


@pytest.mark.slow
def test_direct_lighting_in_the_cornell_box_matches_mitsuba_prb_projective():
    """Second independent-estimator check, with shadows: the Cornell box at max_depth 2 (the
    moving smooth sphere casts a shadow; primary + direct + interior terms). Tiles agree with
    Mitsuba's prb_projective (|z| < 4 on signal tiles, mean z² < 2) and so do the sums."""
    import dataclasses
    from psdr_cli.rendering.estimate import prepare
    exp = load_experiment(REPO / "configs" / "validation" / "cornell.yaml")
    exp = dataclasses.replace(exp, scene=dataclasses.replace(exp.scene, max_depth=2))
    scene, parameter, edges, settings = prepare(exp)
    mi.set_log_level(mi.LogLevel.Error)
    settings = dataclasses.replace(settings.with_estimator(spp=512, primary_spp=512, boundary_spp=512), seed=11)
    passes = None
    for term in TERMS:
        est = forward_gradient(scene, edges, parameter, 0, term, settings, min_passes=8)
        passes = est.passes if passes is None else [a + b for a, b in zip(passes, est.passes)]
    e, e_se = mean_and_error(block_sums(passes, 4))
    m, m_se = mean_and_error(block_sums(mitsuba_projective(scene, parameter, 0, 1024, seed=5, batches=8,
                                                           max_depth=2), 4))
    z = (e - m) / np.sqrt(e_se ** 2 + m_se ** 2 + 1e-30)
    signal = np.abs(m) > 5 * m_se
    assert signal.sum() >= 8
    assert np.all(np.abs(z[signal]) < 4), z
    assert np.mean(z[np.abs(m) + np.abs(e) > 0] ** 2) < 2.0, z
    assert abs(e.sum() - m.sum()) < 3 * np.sqrt((e_se ** 2).sum() + (m_se ** 2).sum())
