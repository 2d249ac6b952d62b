"""The terms of dI/dθ and the random-number streams of every sampled image.

A term is registered by its name in :data:`psdr_cli.config.TERMS` (the vocabulary experiment
files are checked against, in order); the module of this package with that name declares its
:class:`~.term.Term` as ``TERM``. Adding a term is its module plus its name in that tuple. A term
whose pass over a batch can be recorded (``dr.freeze``) has a module ``recorded_<name>.py``
declaring its part as ``PART`` (:class:`~.recording.RecordedPart`), and its name in
:data:`RECORDED`.

Streams (the last argument of :func:`~.passes.pass_seed`) keep images from sharing random
numbers: renders 0, each term its own (interior 1, primary 2, direct 3, indirect 4), Mitsuba's
renders 9, the adjoint renders of an optimisation 10, the coverage images of masked views 11
(hits) and 12 (silhouettes). They are checked to differ on import.
"""
from __future__ import annotations

from importlib import import_module

from ..config.vocabularies import TERMS as NAMES
from .term import Term

#: Random-number stream of primal renders (:func:`psdr_cli.rendering.render.render_view`).
RENDER_STREAM = 0
#: Random-number stream of Mitsuba's renders (``estimator.engine: mitsuba``).
MITSUBA_STREAM = 9
#: Random-number stream of an optimisation's adjoint renders (``optimize.adjoint_spp``).
ADJOINT_STREAM = 10
#: Random-number streams of the coverage images (:mod:`.coverage`): camera-ray hits, silhouettes.
COVERAGE_STREAMS = (11, 12)

#: The terms, in :data:`psdr_cli.config.TERMS` order.
TERMS: tuple[Term, ...] = tuple(import_module(f"{__package__}.{name}").TERM for name in NAMES)
#: Names of the terms a guide can serve.
GUIDED = tuple(t.name for t in TERMS if t.guided)
#: The term whose primal value is the rendered image (the recorded iteration's batch renders it).
RENDERING = next(t.name for t in TERMS if t.renders)
#: The terms with a recorded part, in the order their backward passes run.
RECORDED = ("direct", "primary", "indirect")
#: {term name: the class of its recorded part} (module ``recorded_<name>.py``), in :data:`RECORDED` order.
RECORDED_PARTS = {name: import_module(f"{__package__}.recorded_{name}").PART for name in RECORDED}

_BY_NAME = {t.name: t for t in TERMS}


def term(name: str) -> Term:
    """The term called ``name``."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise ValueError(f"unknown term {name!r} (expected one of {', '.join(NAMES)})") from None


def _check():
    misnamed = [(n, t.name) for n, t in zip(NAMES, TERMS) if n != t.name]
    if misnamed:
        raise RuntimeError(f"estimators/{misnamed[0][0]}.py declares TERM {misnamed[0][1]!r}")
    streams = [RENDER_STREAM, MITSUBA_STREAM, ADJOINT_STREAM, *COVERAGE_STREAMS] + [t.stream for t in TERMS]
    if len(set(streams)) != len(streams):
        raise RuntimeError(f"random-number streams are shared: {streams}")


_check()
