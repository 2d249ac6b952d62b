"""One loss path: the recorded iteration (psdr_cli/optimisation/frozen_batch.py) takes its loss from the
losses (psdr_cli/losses) as the traced one does. A loss added the README's way with a recorded
form is summed there; one without makes ``refusal`` name it, and the traced iteration serves the
run: no loss is left out of an iteration."""
from __future__ import annotations

from dataclasses import replace

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from psdr_cli.losses import registry
from psdr_cli.losses.loss import Loss, RecordedLoss
from psdr_cli.optimisation import iteration
from psdr_cli.optimisation.frozen_batch import FrozenBatch, refusal
from psdr_cli.support import backend
from psdr_cli.support.jitarray import jit_array
from test_frozen_batch import iteration_gradient
from test_frozen_batch import setup as sphere_setup

#: The throwaway loss's weight: its share of the loss is then more than half (targets uniform in
#: [0, 0.6] against the render of the spheres), far above the rounding the tolerances allow.
L2_WEIGHT = 4.0


def view_l2(view, optimize) -> mi.Float:
    """c·mean (I − T)², with an adjoint render P: c·mean (P − T)² + c·mean 2(P − T)·∂I."""
    if view.adjoint is None:
        return L2_WEIGHT * dr.mean(dr.square(view.image - view.target))
    residual = view.adjoint - view.target
    return L2_WEIGHT * (dr.mean(dr.square(residual)) +
                        dr.mean(2.0 * residual * (view.image - dr.detach(view.image))))


def recorded_l2(P: mi.Float, T: mi.Float, primal: bool) -> tuple:
    """(c·Σ (P − T)² / N, 2c·(P − T) / N), N the batch's values."""
    residual = P - T
    scale = L2_WEIGHT / dr.width(P)
    return dr.sum(dr.square(residual)) * scale, 2.0 * residual * scale


def l2_loss(recorded: bool, applies=None) -> Loss:
    """The throwaway L2 loss, with its recorded form or without one (``applies``: its predicate)."""
    more = {} if applies is None else {"applies": applies}
    return Loss("l2", "image L2", view_l2, recorded=RecordedLoss(recorded_l2) if recorded else None, **more)


def with_loss(monkeypatch, loss: Loss):
    """The registry with ``loss`` added after the others, as a module named in NAMES adds it."""
    monkeypatch.setattr(registry, "NAMES", registry.NAMES + (loss.name,))
    monkeypatch.setattr(registry, "LOSSES", registry.LOSSES + (loss,))


@pytest.mark.parametrize("adjoint_spp", [None, 0], ids=["adjoint-render", "no-adjoint-render"])
def test_a_recorded_form_is_summed_by_the_recorded_iteration(monkeypatch, adjoint_spp):
    """One loop iteration with L1 + L2, recorded and traced (with the experiment's adjoint render,
    and without one: P is then the AD render's own primal): the same loss and gradient, to the
    bounds of tests/test_frozen_batch.py::test_the_frozen_iteration_is_the_traced_iteration (the
    camera rays' rounding; measured there 5.3·10⁻⁷ and 1.7·10⁻⁷ against 10⁻⁵ and 10⁻⁴, here 0 and
    2.4·10⁻⁷). The L2 part (58 % of the loss, and it changes the gradient by about its own L1
    norm) is checked to be far past those bounds: an iteration that left it out fails."""
    l1_only = iteration_gradient(False, 3, adjoint_spp)
    with_loss(monkeypatch, l2_loss(recorded=True))
    a, _, ga = iteration_gradient(True, 3, adjoint_spp)  # (asserts that the three recorded parts ran)
    b, _, gb = iteration_gradient(False, 3, adjoint_spp)
    assert abs(b.loss - l1_only[0].loss) > 1e3 * 1e-5 * b.loss  # the L2 part counts
    assert np.abs(gb - l1_only[2]).sum() > 1e3 * 1e-4 * np.abs(gb).sum()
    assert np.isclose(a.loss, b.loss, rtol=1e-5), (a.loss, b.loss)
    assert np.abs(ga - gb).sum() <= 1e-4 * np.abs(gb).sum(), np.abs(ga - gb).sum() / np.abs(gb).sum()


def test_a_loss_without_a_recorded_form_is_named_and_the_traced_iteration_serves_the_run(monkeypatch):
    """A loss with no recorded form that applies to the run: ``refusal`` names it, and the loop's
    iteration is the traced one (nothing recorded; the traced loop's loss, L2 part included); one
    that does not apply (its ``applies`` false) leaves the recorded iteration serving."""
    exp, problem, engine, stage = sphere_setup()
    cfg = exp.optimize
    assert refusal(problem, stage, cfg, engine, engine.settings, 4) is None
    with pytest.MonkeyPatch.context() as mp:
        with_loss(mp, l2_loss(recorded=False, applies=lambda stage, optimize: False))
        assert refusal(problem, stage, cfg, engine, engine.settings, 4) is None
    with_loss(monkeypatch, l2_loss(recorded=False))
    assert refusal(problem, stage, cfg, engine, engine.settings, 4) == "loss 'l2' has no recorded form"
    problem.release()
    losses = []
    for frozen in (FrozenBatch(), None):
        exp, problem, engine, stage = sphere_setup()
        loop = iteration.Loop(exp.optimize, engine, 10, print, frozen=frozen)
        with backend.optimization_threads():
            losses.append(iteration.iterate(problem, loop, stage, iteration.GuideCache(), 0).loss)
        problem.release()
        assert frozen is None or frozen.n_recordings == 0
    assert np.isclose(losses[0], losses[1], rtol=1e-6)  # (equal on LLVM; the L2 part is most of it)


@pytest.mark.parametrize("weighted", [False, True])
def test_masks_and_pixel_weights_are_refused_by_the_losses_they_concern(weighted):
    """A masked stage: the silhouette loss applies and has no recorded form; pixel weights: the L1
    loss's recorded form takes none. Each refusal names its loss."""
    exp, problem, engine, stage = sphere_setup()
    cfg = exp.optimize
    W, H = exp.scene.width, exp.scene.height
    ones = [jit_array(mi.Float, np.ones(W * H * (3 if weighted else 1), np.float32)) for _ in stage.arrays]
    stage = replace(stage, weights=ones) if weighted else replace(stage, masks=ones)
    reason = refusal(problem, stage, cfg, engine, engine.settings, 4)
    assert reason is not None
    assert ("'l1'" in reason and "weights" in reason) if weighted else "'silhouette'" in reason
    problem.release()
