"""``evaluate``: the reference mesh and the samples of ``psdr evaluate``'s shape error."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .limits import MAX_EVAL_SAMPLES, MIN_EVAL_SAMPLES
from .values import Parser, Section, integer, path_relative_to


@dataclass
class EvaluateConfig:
    reference: Path | None = None
    samples: int = 100_000
    seed: int = 0


def parse_evaluate(base: Path) -> Parser:
    def parse(value, where) -> EvaluateConfig:
        sec = Section(value, where)
        e = EvaluateConfig()
        e.reference = sec.get("reference", path_relative_to(base), None)
        e.samples = sec.get("samples", integer(MIN_EVAL_SAMPLES, MAX_EVAL_SAMPLES), e.samples)
        e.seed = sec.get("seed", integer(0), e.seed)
        sec.done()
        return e
    return parse
