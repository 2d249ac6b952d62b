"""``estimator.guiding: auto``: the guide each boundary term gets, from the size of one pass.

Guiding pays when its build (about a fixed share of one pass, :mod:`.targets`) and its costlier
passes are outweighed by lower variance per sample. Both grow with the image: a pass of
L = W · H · boundary_spp lanes spreads its samples over more of the image's edges, and the
guide concentrates them where the integrand is non-zero. The rule, from
``benchmarks/guiding.py`` (docs/benchmarks/guiding.md, equal wall time, build included):

- direct and indirect term: ``kdtree`` when L ≥ MIN_LANES (2¹⁶), else ``none``. Measured: the
  Kd-tree reached 0.22–0.45× the unguided MIS error at 32² × 64 spp (L = 2¹⁶, Cornell box with
  a glass sphere, both terms guided; the indirect term alone: 0.34×), 48² × 64 spp (sun-lit
  glossy bunny, soft shadow) and 128² × 64 spp (all three). Smaller passes are not measured and
  stay unguided (a Kd-tree's first batch has at least 2¹⁷ samples, two such passes);
- the grid guide is never chosen (it was worse than the Kd-tree in every measured case but one).

Other values of ``estimator.guiding`` (none, grid, kdtree) apply to every term unchanged.

In the optimisation loop ``auto`` guides no term (:func:`in_loop`). The rule above is measured
on forward-mode gradient images; the loop steps with Adam on reverse-mode gradients, and there
no guide paid at equal time in any reconstruction measured (docs/guiding.md, "Guiding in the
loop"): the runs were limited by their iteration count, not by gradient noise (four times the
boundary samples, or four times the vertices, gave the same shape per iteration), and a
lower-variance gradient only enlarged Adam's effective step. With both estimators at their best
step (``benchmarks/guided_loop.py``) the loop-fed Kd-tree ended 1.09× unguided's Chamfer-L1 at
the Fig. 10 shadow experiment's scale, 1.14–1.16× at 1–2 boundary spp and 1.03× at four and at
sixteen times the vertices: no measured scale crosses 1.
"""
from __future__ import annotations

from ..estimators.registry import GUIDED

#: lanes of one boundary pass (W·H·boundary_spp) from which a boundary term is guided
MIN_LANES = 1 << 16
#: the terms a guide can serve (``Term.guided``)
GUIDED_TERMS = GUIDED


def choose(term: str, lanes: int) -> str:
    """The guide ``auto`` picks for ``term`` when one boundary pass has ``lanes`` lanes."""
    return "kdtree" if term in GUIDED_TERMS and lanes >= MIN_LANES else "none"


def decide(guiding: str, pixels: int, boundary_spp: int, loop: bool = False) -> dict:
    """{term: guide kind} for every guidable term (``guiding`` auto or a kind) on images of
    ``pixels`` pixels; ``loop``: in the optimisation loop (:func:`in_loop`). Made once, where the
    settings of an estimate are made (:class:`psdr_cli.estimate.Settings`); the guides, the
    stages and the report read it."""
    guiding = in_loop(guiding) if loop else guiding
    return {t: choose(t, pixels * boundary_spp) if guiding == "auto" else guiding for t in GUIDED_TERMS}


def in_loop(guiding: str) -> str:
    """What ``estimator.guiding`` means in the optimisation loop: ``auto`` is ``none`` there
    (module docstring); an explicit kind is kept."""
    return "none" if guiding == "auto" else guiding


def describe(guiding: str, kinds: dict, lanes: int, loop: bool = False) -> str:
    """One line: what each boundary term is guided with (``kinds``, as :func:`decide` made them,
    for the requested terms), e.g. ``guiding auto: direct kdtree, indirect none (pass of 262144
    lanes)``; ``loop``: in the optimisation loop (:func:`in_loop`)."""
    if loop and guiding == "auto":
        return "guiding auto: none in the optimisation loop (guides did not pay there: docs/guiding.md)"
    if not kinds:
        return f"guiding {guiding}: no boundary term requested"
    chosen = ", ".join(f"{t} {k}" for t, k in kinds.items())
    return f"guiding {guiding}: {chosen} (boundary pass of {lanes} lanes)"
