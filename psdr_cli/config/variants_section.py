"""Estimator variants: the runs of ``optimize.variants`` and the entries of ``compare.variants``."""
from __future__ import annotations

from dataclasses import dataclass

from .values import Parser, Section, boolean, choice, integer, number, per_stage, string
from .vocabularies import COMMAND_FOLDERS, ENGINES, GUIDINGS, SAMPLINGS


@dataclass
class Variant:
    """One estimator variant: a run of an ablation (``optimize.variants``) or an entry of a
    comparison (``compare.variants``). ``None`` keeps the experiment's value. ``seed`` gives a
    run another seed (replicate runs; the targets do not depend on it); ``passes`` gives a
    comparison entry a fixed number of passes (equal samples) instead of the time budget;
    ``learning_rate`` and ``lambda`` give a run its own step (a sweep of step sizes per estimator)."""
    label: str
    guiding: str | None = None
    sampling: str | None = None
    edge_sort: bool | None = None
    seed: int | None = None
    passes: int | None = None
    engine: str | None = None
    learning_rate: float | None = None     # a run's own Adam step (step-size sweeps)
    lambda_: tuple | None = None           # a run's own LargeSteps λ, one value or one per stage


def parse_variant(value, where, guiding=None, sampling=None, edge_sort=None) -> Variant:
    """A variant mapping; the keyword arguments are the defaults of the keys it leaves out."""
    sec = Section(value, where)
    v = Variant(label=sec.get("label", string),
                guiding=sec.get("guiding", choice(*GUIDINGS), guiding),
                sampling=sec.get("sampling", choice(*SAMPLINGS), sampling),
                edge_sort=sec.get("edge_sort", boolean, edge_sort))
    return v, sec


#: Names a variant's run folder may not have: they are psdr's own entries of ``<output>/<name>/``.
RESERVED_LABELS = {**{c: f"psdr {c.replace('_', '-')}'s output folder" for c in COMMAND_FOLDERS},
                   "reference": "the report's reference.ply", "checkpoints": "a run's checkpoint folder",
                   "previews": "a run's preview folder", "targets": "a run's target images"}


def run_variant_parser(stages: int) -> Parser:
    """A run of ``optimize.variants``: estimator keys, ``seed``, ``engine``, and its own
    ``learning_rate`` and ``lambda`` (one value or one per remesh stage, of ``stages``)."""
    def parse(value, where) -> Variant:
        v, sec = parse_variant(value, where)
        if not v.label or "/" in v.label or v.label in (".", "..") or v.label != v.label.strip():
            raise where.child("label").fail(f"expected a plain folder name, got '{v.label}'")
        if v.label in RESERVED_LABELS:
            raise where.child("label").fail(f"'{v.label}' is taken ({RESERVED_LABELS[v.label]}); choose another label")
        v.seed = sec.get("seed", integer(0), None)
        v.engine = sec.get("engine", choice(*ENGINES), None)
        v.learning_rate = sec.get("learning_rate", number(positive=True), None)
        v.lambda_ = sec.get("lambda", per_stage(number(minimum=0), stages), None)
        sec.done()
        return v
    return parse


def parse_compare_variant(value, where) -> Variant:
    """A comparison entry: unguided, MIS and unsorted unless it says otherwise."""
    v, sec = parse_variant(value, where, guiding="none", sampling="mis", edge_sort=False)
    v.passes = sec.get("passes", integer(1), None)
    sec.done()
    return v


def unique_labels(variants, where):
    labels = [v.label for v in variants]
    if len(set(labels)) != len(labels):
        raise where.child("variants").fail("variant labels must be unique")
