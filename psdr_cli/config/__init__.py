"""Experiment files: YAML parsed into typed objects and validated, one module per idea.

:mod:`.experiment_file` reads a file into an :class:`~.experiment_file.Experiment` and runs the
checks across sections; each section has its module with its dataclasses and parser
(:mod:`.scene` with :mod:`.cameras`, :mod:`.emitters` and :mod:`.objects`; :mod:`.parameter`,
:mod:`.estimator`, :mod:`.optimize` with :mod:`.dataset`, :mod:`.unknowns` and :mod:`.variants`;
:mod:`.compare`, :mod:`.evaluate`). Below them: :mod:`.values` (a YAML mapping being read and the
parsers of one value), :mod:`.vocabularies` (every name a key accepts), :mod:`.limits` (resource
limits), :mod:`.scene_ids` (psdr's own Mitsuba ids). :mod:`.options` checks command-line options
like the keys they stand for. The key reference is ``docs/config.md``.
"""
