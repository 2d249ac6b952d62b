"""Guides of a term fitted from the optimisation loop's own samples (the term whose
:class:`~psdr_cli.estimators.term.GuideTarget` is ``loop_fed``: the direct term).

The loop's passes of such a term evaluate the guide target F̃ at every sample they draw
(:mod:`psdr_cli.estimators.sample_log`), so a guide can be grown from them with no evaluation of
its own: the Kd-tree of each technique is fitted (:func:`.kdtree.fit_kdtree`) to the samples of
the ``optimize.guide_every`` iterations since the last fit, and the techniques share their edge
profile as built guides do (:func:`.kdtree.share_profiles`). The samples come from earlier
iterations, so the guide an iteration samples with is independent of that iteration's own
random numbers and its estimate stays unbiased (the guide's uniform share ε > 0 covers what the
samples missed). The shape moves a little between the samples and the iterations that use the
guide; that costs efficiency, not correctness.
"""
from __future__ import annotations

import numpy as np

from ..estimators import registry
from ..estimators.sample_log import PER_PASS, SampleLog
from .kdtree import EXPLORE, fit_kdtree, share_profiles, tree_arrays, tree_from_arrays, tree_limits
from .kinds import LOOP_FED

#: samples kept per window and technique (split over the window's passes)
WINDOW_SAMPLES = 32768


def fed_term(kinds: dict) -> str | None:
    """The term among ``kinds`` ({term: guide kind}) whose guides the loop fits to its own
    samples: its :class:`~psdr_cli.estimators.term.GuideTarget` is ``loop_fed`` and its guide kind
    is (:data:`.kinds.LOOP_FED`); None when no term is. At most one (a run's state keeps one
    sample log)."""
    fed = [t for t, kind in kinds.items() if kind in LOOP_FED and registry.term(t).guide.loop_fed]
    if len(fed) > 1:
        raise ValueError(f"terms {', '.join(fed)} are all loop-fed; the loop feeds one term's guides")
    return fed[0] if fed else None


def per_pass_budget(passes: int) -> int:
    """Samples each of ``passes`` passes of a window keeps, so that a window keeps at most
    WINDOW_SAMPLES per technique (16 to PER_PASS per pass)."""
    return int(np.clip(WINDOW_SAMPLES // max(passes, 1), 16, PER_PASS))


def fitted_guides(log: SampleLog, breaks, estimator) -> dict:
    """{technique: Kd-tree} fitted to the samples of ``log`` (techniques whose samples found no
    contribution stay unguided)."""
    k = estimator.kdtree
    guides = {}
    for t in sorted(log.kept):
        u, f, w = log.samples(t)
        if f.any():
            guides[t] = fit_kdtree(u, f, w, breaks=breaks, limits=tree_limits(k),
                                   epsilon=max(estimator.guide_epsilon, EXPLORE), interval_share=k.interval_share)
    shared = share_profiles(guides, breaks, k.technique_share)
    return {t: tree_from_arrays(tree_arrays(g)) for t, g in shared.items()}  # as saved (float32)


def guide_arrays(log: SampleLog) -> dict:
    """A log's guides and kept samples as flat arrays (``tree_<technique>_<name>``,
    ``kept_<technique>_<name>``) for a saved state."""
    out = {f"tree_{t}_{k}": v for t, g in log.items() for k, v in tree_arrays(g).items()}
    out.update({f"kept_{k}": v for k, v in log.arrays().items()})
    return out


def log_from_arrays(arrays: dict, per_pass: int) -> SampleLog:
    """The log :func:`guide_arrays` saved: the same guides and the samples kept so far."""
    trees = {}
    for key, value in arrays.items():
        if key.startswith("tree_"):
            t, name = key[5:].split("_", 1)
            trees.setdefault(t, {})[name] = value
    log = SampleLog({t: tree_from_arrays(a) for t, a in trees.items()}, per_pass)
    log.restore({k[5:]: v for k, v in arrays.items() if k.startswith("kept_")})
    return log
