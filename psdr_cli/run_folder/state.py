"""state.npz: everything needed to continue a run, and whether a run can be resumed."""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config.experiment_file import Experiment
from ..errors import PsdrError
from ..support import fileio
from .layout import RunFiles
from .record import same_experiment


@dataclass
class State:
    """Everything needed to continue a run: mesh, optimiser moments, extra unknowns."""
    iteration: int
    V: np.ndarray
    F: np.ndarray
    adam: dict = field(default_factory=dict)     # name -> (t, m, v)
    values: dict = field(default_factory=dict)   # extra unknowns: albedo (3,), envmap angle (1,)
    seconds: float = 0.0                         # optimisation time so far
    u: np.ndarray | None = None                  # large-steps latent (V = solve(u) reproduces the saved V exactly)
    basis: np.ndarray | None = None              # vertices LargeSteps was built from (orders u)
    guide_V: np.ndarray | None = None            # vertices the current guides were built from
    guide_values: dict = field(default_factory=dict)  # extra unknowns when they were built
    uv: np.ndarray | None = None                 # per-vertex texture coordinates (albedo.texture)
    guide_arrays: dict = field(default_factory=dict)  # loop-fed guides and their kept samples

    def save(self, path: Path):
        """Written atomically; refuses NaN or infinite values (nothing non-finite is ever saved)."""
        arrays = {"V": self.V, "F": self.F, "u": self.u, "basis": self.basis}
        if self.uv is not None:
            arrays["uv"] = self.uv
        if self.guide_V is not None:
            arrays["guide_V"] = self.guide_V
            for k, v in self.guide_values.items():
                arrays[f"guidevalue_{k}"] = v
        for k, v in self.guide_arrays.items():
            arrays[f"guidearr_{k}"] = v
        for k, (t, m, v) in self.adam.items():
            arrays[f"adam_{k}_m"], arrays[f"adam_{k}_v"] = m, v
        for k, v in self.values.items():
            arrays[f"value_{k}"] = v
        for k, a in arrays.items():
            fileio.check_finite(path, a, f"state '{k}'")
        meta = {"iteration": self.iteration, "seconds": self.seconds,
                "adam_t": {k: int(t) for k, (t, _, _) in self.adam.items()}}
        with fileio.atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, meta=np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays)

    @staticmethod
    def load(path: Path) -> "State":
        try:
            with np.load(path) as z:
                meta = json.loads(bytes(z["meta"]).decode())
                adam = {k: (t, z[f"adam_{k}_m"], z[f"adam_{k}_v"]) for k, t in meta["adam_t"].items()}
                values = {k[6:]: z[k] for k in z.files if k.startswith("value_")}
                guide_values = {k[11:]: z[k] for k in z.files if k.startswith("guidevalue_")}
                state = State(meta["iteration"], z["V"], z["F"], adam, values, meta.get("seconds", 0.0),
                              z["u"], z["basis"], z["guide_V"] if "guide_V" in z.files else None, guide_values,
                              z["uv"] if "uv" in z.files else None,
                              {k[9:]: z[k] for k in z.files if k.startswith("guidearr_")})
                arrays = [state.V, state.u, state.basis, *values.values(), *([state.uv] if state.uv is not None else []),
                          *(a for _, m, v in adam.values() for a in (m, v))]
        except Exception as exc:  # noqa: BLE001 - a damaged state file
            raise PsdrError(f"{path}: cannot read the saved state ({type(exc).__name__}); "
                            f"run without --resume to start over (the run is moved aside)") from None
        if not all(np.isfinite(np.asarray(a, float)).all() for a in arrays):
            raise PsdrError(f"{path}: the saved state holds NaN or infinite values; run without --resume to start over "
                            "(the run is moved aside)")
        return state


def resumable_state(files: RunFiles, exp: Experiment, total: int, resume: bool, warn) -> State | None:
    """With ``resume``: the run's saved state, if there is one and it belongs to ``exp``; None for
    a fresh start (the caller moves a run found in the folder aside once the inputs are read:
    :func:`keep_previous_run`)."""
    if not resume:
        return None
    state = State.load(files.state) if files.state.exists() else None
    if state is None:
        warn(f"--resume: no saved state in {files.root}; starting from the beginning")
    if state is not None and not same_experiment(files, exp):
        warn(f"--resume: {exp.file.name} changed since the run in {files.root} was saved; starting from the "
             f"beginning (the old run is moved aside)")
        state = None
    if state is not None and state.iteration > total:
        raise PsdrError(f"--iterations: {total} is fewer than the {state.iteration} iterations the run in "
                        f"{files.root} has done (ask for at least {state.iteration}, or run without --resume to "
                        f"start afresh: the run is then moved aside, not deleted)")
    return state
