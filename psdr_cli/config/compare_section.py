"""``compare``: the variants ``psdr compare`` times against a reference."""
from __future__ import annotations

from dataclasses import dataclass

from .estimator_section import term_names
from .limits import MAX_PASSES
from .values import Section, integer, list_of, number
from .variants_section import parse_compare_variant, unique_labels


@dataclass
class CompareConfig:
    variants: list                       # of Variant (guiding, sampling, edge_sort always set)
    terms: tuple = ("direct",)
    view: int = 0
    budget_seconds: float = 6.0
    trials: int = 2
    reference_passes: int = 1024


def parse_compare(value, where) -> CompareConfig:
    sec = Section(value, where)
    c = CompareConfig(variants=sec.get("variants", list_of(parse_compare_variant, min_len=1)))
    unique_labels(c.variants, where)
    c.terms = sec.get("terms", term_names, c.terms)
    c.view = sec.get("view", integer(0), c.view)
    c.budget_seconds = sec.get("budget_seconds", number(positive=True), c.budget_seconds)
    c.trials = sec.get("trials", integer(1), c.trials)
    c.reference_passes = sec.get("reference_passes", integer(2, MAX_PASSES), c.reference_passes)
    sec.done()
    return c
