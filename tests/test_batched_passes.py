"""Forward-mode passes traced as one wavefront (issue 38): ``forward_gradient`` hands a term that
traces several views at once its view once per pass, so that a group of passes is one trace, one
set of kernels and one forward sweep. Each pass must stay an independent estimate of dI/dθ with
the distribution of a pass traced alone: the passes' mean and spread agree with passes traced one
by one, and a single pass is the pass traced alone bit for bit."""
from __future__ import annotations

import copy
from dataclasses import replace
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy.stats import chi2, f

from psdr_cli.config.options import with_estimator
from psdr_cli.estimators.passes import AD_LANES
from psdr_cli.experiment.load import load_experiment, parse_experiment
from psdr_cli.rendering import estimate
from psdr_cli.rendering.estimate import forward_gradient, pass_groups, prepare, term_image, term_passes, term_seed
from psdr_cli.support import backend
from conftest import bit_reproducible
from test_direct_boundary import SHADOW

#: light reaches the floor the camera sees only by way of a wall: the indirect term's scene
INDIRECT = Path(__file__).resolve().parents[1] / "configs" / "validation" / "indirect.yaml"

R = 24
PASSES = 16
#: tiles per side of the tile sums compared
BLOCKS = 6


def shadow_setup(tmp_path, **estimator):
    """The occluder-and-floor scene of test_direct_boundary at R × R, θ = the occluder's
    x-translation (its silhouette, its shadow and its shading all move)."""
    data = copy.deepcopy(SHADOW)
    data["seed"] = 7
    data["scene"]["film"] = {"width": R, "height": R}
    data["parameter"] = {"object": "occ", "kind": "translate", "axis": [1, 0, 0]}
    data["estimator"] = {"spp": 64, "primary_spp": 64, "boundary_spp": 64, "guiding": "none", **estimator}
    exp = parse_experiment(data, tmp_path / "shadow.yaml", cwd=tmp_path)
    return prepare(exp)


def indirect_setup(tmp_path):
    """configs/validation/indirect.yaml at R × R (θ: the black ball moves up; max_depth 3)."""
    exp = load_experiment(INDIRECT)
    exp = replace(exp, scene=replace(exp.scene, width=R, height=R))
    return prepare(with_estimator(exp, spp=64, primary_spp=64, boundary_spp=1024, guiding="none"))


SETUPS = {"interior": shadow_setup, "primary": shadow_setup, "direct": shadow_setup, "indirect": indirect_setup}


def passes_one_by_one(scene, edges, parameter, term, settings, min_passes):
    """The passes of ``term`` traced one at a time (the estimator before passes were grouped)."""
    counts = term_passes(term, settings, R * R, min_passes)
    images = []
    for p, spp in enumerate(counts):
        theta = mi.Float(0.0)
        dr.enable_grad(theta)
        parameter.apply(theta)
        img = term_image(scene, edges, 0, term, spp, term_seed(settings, 0, p, term), settings)
        dr.forward(theta)
        images.append(np.asarray(dr.grad(img), np.float64).reshape(R, R, 3))
        parameter.reset()
    return counts, images


def tiles(image) -> np.ndarray:
    """Sums of an (R, R, 3) image over BLOCKS × BLOCKS tiles."""
    b = R // BLOCKS
    return image.sum(-1).reshape(BLOCKS, b, BLOCKS, b).sum(axis=(1, 3)).ravel()


def test_pass_groups_join_equal_passes_that_fit_in_one_ad_pass():
    assert pass_groups([3, 3, 3, 2, 2], 100, True) == [[0, 1, 2], [3, 4]]
    per_pass = AD_LANES // 2  # lanes of one pass at 1 spp: two fit
    assert pass_groups([1, 1, 1, 1, 1], per_pass, True) == [[0, 1], [2, 3], [4]]
    assert pass_groups([3, 3, 2], 100, False) == [[0], [1], [2]]
    assert pass_groups([5], AD_LANES, True) == [[0]]  # more lanes than one AD pass holds: alone


@pytest.mark.parametrize("term", list(SETUPS))
def test_grouped_passes_are_independent_passes_of_the_estimator(tmp_path, monkeypatch, term):
    """Tile sums of dI/dθ per pass (6 × 6 tiles, 16 passes of 4 spp, 64 for the indirect term,
    traced in four groups): the grouped passes' mean agrees with the one-by-one passes' mean
    (|z| < 4.5 per tile the term reaches, and Σz² below the
    chi-square's 0.999 quantile) and their spread matches (the ratio of the total variances inside
    the F distribution's central 0.999 for 15 and 15 degrees of freedom, [0.19, 5.3]: a few tiles
    carry most of the variance, 0.33-2.19 over six seeds); passes that shared their random
    numbers would have no spread, passes written into one image or given every pass's samples a
    far larger or smaller one. Interior, primary and direct on the shadow scene, indirect on the
    scene lit by way of a wall."""
    scene, parameter, edges, settings = SETUPS[term](tmp_path)
    counts, single = passes_one_by_one(scene, edges, parameter, term, settings, PASSES)
    # an AD pass that holds four passes: four groups, so that passes of different groups are compared too
    monkeypatch.setattr(estimate, "AD_LANES", 4 * R * R * counts[0])
    assert [len(g) for g in pass_groups(counts, R * R, True)] == [4, 4, 4, 4]
    grouped = forward_gradient(scene, edges, parameter, 0, term, settings, PASSES)
    assert len(grouped.passes) == len(single) == PASSES
    # grouped: other random numbers than the passes traced alone (more than the last bits that
    # scatter-adds on two threads change), and no two passes alike
    assert np.abs(grouped.passes[0] - single[0]).max() > 1e-3 * np.abs(single[0]).max()
    assert len({p.tobytes() for p in grouped.passes}) == PASSES
    a = np.array([tiles(img) for img in grouped.passes])
    b = np.array([tiles(img) for img in single])
    se = np.sqrt(a.var(axis=0, ddof=1) / len(a) + b.var(axis=0, ddof=1) / len(b))
    signal = se > 1e-6 * np.abs(b).max()  # tiles the term reaches (elsewhere exactly 0)
    assert signal.sum() >= 4
    z = (a.mean(axis=0) - b.mean(axis=0))[signal] / se[signal]
    assert np.abs(z).max() < 4.5 and np.sum(z ** 2) < chi2.ppf(0.999, len(z)), z
    ratio = a.var(axis=0, ddof=1).sum() / b.var(axis=0, ddof=1).sum()
    dof = PASSES - 1
    assert f.ppf(0.0005, dof, dof) < ratio < f.ppf(0.9995, dof, dof), ratio


@bit_reproducible
def test_a_single_pass_is_the_pass_traced_alone(tmp_path):
    """With one Dr.Jit thread (scatter-adds then add in one order, as in the optimisation loop)."""
    with backend.optimization_threads():
        for term, setup in SETUPS.items():
            scene, parameter, edges, settings = setup(tmp_path)
            one = forward_gradient(scene, edges, parameter, 0, term, settings, 1)
            _, alone = passes_one_by_one(scene, edges, parameter, term, settings, 1)
            assert len(one.passes) == 1 and np.array_equal(one.passes[0], alone[0]), term


def test_progress_counts_every_sample_once(tmp_path):
    scene, parameter, edges, settings = shadow_setup(tmp_path)
    advanced = []
    forward_gradient(scene, edges, parameter, 0, "primary", settings, 5, progress=advanced.append)
    assert sum(advanced) == settings.primary_spp and len(advanced) == 2  # 64 spp in 5 passes: 13 + 13 + 13 + 13 + 12
