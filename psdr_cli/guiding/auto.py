"""Owns ``estimator.guiding: auto``: the guide each boundary term gets, from the size of one pass.
Reads the guiding setting and the pass size; touches nothing.

A pass of L = W · H · boundary_spp lanes guides the direct and indirect terms with ``kdtree``
when L ≥ :data:`MIN_LANES` (2¹⁶), else with ``none``; the grid guide is never chosen. The rule
and the equal-time measurements behind it are in docs/guiding.md, "guiding: auto". Other values
of ``estimator.guiding`` (none, grid, kdtree) apply to every term unchanged.

In the optimisation loop ``auto`` guides no term (:func:`in_loop`): there no guide paid at equal
time in any reconstruction measured (docs/guiding.md, "Guiding in the loop")."""
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
    settings of an estimate are made (:class:`psdr_cli.rendering.estimate.Settings`); the guides, the
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
