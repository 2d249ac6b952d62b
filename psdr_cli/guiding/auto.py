"""``estimator.guiding: auto``: the guide each boundary term gets, from the size of one pass.

Guiding pays when its build (about a fixed share of one pass, :mod:`.targets`) and its costlier
passes are outweighed by lower variance per sample. Both grow with the image: a pass of
L = W · H · boundary_spp lanes spreads its samples over more of the image's edges, and the
guide concentrates them where the integrand is non-zero. The rule, from
``benchmarks/guiding.py`` (docs/benchmarks/guiding.md, equal wall time, build included):

- direct term: ``kdtree`` when L ≥ DIRECT_MIN_LANES (2¹⁸), else ``none``. Measured: at 128²
  × 64 spp (L = 2²⁰) the Kd-tree wins on all three Fig. 6 scenes; at 48² × 64 spp (L ≈ 2¹⁷) it
  wins on the soft shadow and loses on the sun-lit glossy bunny, so small passes stay unguided;
  the threshold between the two measured sizes is interpolated;
- indirect term: ``kdtree`` when L ≥ INDIRECT_MIN_LANES (2¹⁶): on the Cornell box with a glass
  sphere guiding the indirect term cut the error several times at 32² and at 128² (its
  integrand is much sparser than its cost: most random subpaths carry nothing);
- the grid guide is never chosen (it was worse than the Kd-tree in every measured case but one).

Other values of ``estimator.guiding`` (none, grid, kdtree) apply to every term unchanged.
"""
from __future__ import annotations

#: lanes of one boundary pass from which the direct term is guided (W·H·boundary_spp)
DIRECT_MIN_LANES = 1 << 18
#: lanes of one boundary pass from which the indirect term is guided
INDIRECT_MIN_LANES = 1 << 16
#: the terms a guide can serve
GUIDED_TERMS = ("direct", "indirect")


def choose(term: str, lanes: int) -> str:
    """The guide ``auto`` picks for ``term`` when one boundary pass has ``lanes`` lanes."""
    threshold = DIRECT_MIN_LANES if term == "direct" else INDIRECT_MIN_LANES
    return "kdtree" if lanes >= threshold else "none"


def resolve(guiding: str, terms, pixels: int, boundary_spp: int) -> dict:
    """{term: guide kind} for the boundary terms among ``terms`` (``guiding`` auto or a kind)."""
    return {t: choose(t, pixels * boundary_spp) if guiding == "auto" else guiding
            for t in GUIDED_TERMS if t in terms}


def describe(guiding: str, terms, pixels: int, boundary_spp: int) -> str:
    """One line: what each boundary term is guided with, e.g.
    ``guiding auto: direct kdtree, indirect none (pass of 262144 lanes)``."""
    kinds = resolve(guiding, terms, pixels, boundary_spp)
    if not kinds:
        return f"guiding {guiding}: no boundary term requested"
    chosen = ", ".join(f"{t} {k}" for t, k in kinds.items())
    return f"guiding {guiding}: {chosen} (boundary pass of {pixels * boundary_spp} lanes)"
