"""The runs of an experiment: one per ``optimize.variants`` entry, each with its own folder."""
from __future__ import annotations

from dataclasses import replace

from ..config.experiment_file import Experiment
from ..config.options import with_estimator
from ..errors import PsdrError


def variant_experiments(exp: Experiment, labels=None) -> list:
    """[(label, experiment)] of the runs of ``exp``: itself (label None) without
    ``optimize.variants``, else one experiment per variant (all, or those in ``labels``) with
    the variant's estimator keys and the run folder ``<output>/<name>/<label>``."""
    variants = exp.optimize.variants if exp.optimize else ()
    if not variants:
        if labels:
            raise PsdrError(f"{exp.file}: optimize.variants: missing (--variant needs the experiment's variants)")
        return [(None, exp)]
    known = [v.label for v in variants]
    unknown = [l for l in labels or () if l not in known]
    if unknown:
        raise PsdrError(f"--variant: unknown variant '{unknown[0]}' (variants of {exp.file.name}: {', '.join(known)})")
    return [(v.label, replace(with_estimator(exp, guiding=v.guiding, sampling=v.sampling, edge_sort=v.edge_sort,
                                                     engine=v.engine),
                              output=exp.run_dir, name=v.label, seed=exp.seed if v.seed is None else v.seed,
                              optimize=variant_optimize(exp.optimize, v, exp.seed)))
            for v in variants if not labels or v.label in labels]


def variant_optimize(opt, v, target_seed: int):
    """The optimize section of variant ``v``'s run: its own learning rate and λ where it sets
    them, and the base experiment's seed for the targets (shared by every variant)."""
    return replace(opt, target_seed=target_seed,
                   learning_rate=opt.learning_rate if v.learning_rate is None else v.learning_rate,
                   lambda_=opt.lambda_ if v.lambda_ is None else v.lambda_)


def existing_runs(exp: Experiment, command: str) -> list:
    """[(label, run folder)] of every run of ``exp``; refuses runs that were never started."""
    runs = [(label, run.run_dir) for label, run in variant_experiments(exp)]
    missing = [str(folder) for _, folder in runs if not (folder / "log.csv").exists()]
    if missing:
        raise PsdrError(f"{command}: run {missing[0]} does not exist yet (run `psdr optimize {exp.file}` first)")
    return runs
