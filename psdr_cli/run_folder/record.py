"""run.json: the record of which experiment a run belongs to (its fingerprint and version)."""
from __future__ import annotations

import json

from ..config.experiment_file import Experiment
from .fingerprint import FINGERPRINT_VERSION, run_fingerprint
from .fingerprint_v1 import fingerprint_v1
from .layout import RunFiles


def run_record(exp: Experiment) -> dict:
    """The contents of run.json: the fingerprint of ``exp`` and its version."""
    return {"fingerprint": run_fingerprint(exp), "fingerprint_version": FINGERPRINT_VERSION}


def same_experiment(files: RunFiles, exp: Experiment) -> bool:
    """Whether the run in ``files`` belongs to ``exp``: its run.json holds the fingerprint of
    ``exp`` of the version it records (run.json without a version: :func:`fingerprint_v1`). A run
    folder without a readable run.json is taken as belonging to it."""
    try:
        record = json.loads(files.run.read_text())
        saved = record["fingerprint"]
    except (OSError, ValueError, KeyError, TypeError):
        return True
    version = record.get("fingerprint_version", 1)
    if version == FINGERPRINT_VERSION:
        return saved == run_fingerprint(exp)
    if version == 1:
        return saved == fingerprint_v1(exp)
    return False
