"""Owns Ray sweeps (``--ray``): every run of an ablation, or every variant of a comparison, as one
Ray task. Reads the experiment and its run folders; starts or joins a Ray instance; writes the run
folders and the comparison's files (in ``copy`` mode the driver is their only writer).

``psdr optimize cfg.yaml --ray [ADDRESS]`` runs each run of :func:`psdr_cli.run_folder.variant_folders.variant_experiments`
(each variant × seed of ``optimize.variants``) as one Ray task calling the same
:func:`psdr_cli.commands.optimize.optimize` as the sequential path; ``psdr compare cfg.yaml --ray`` renders
the reference as one task and measures each variant as one task
(:meth:`psdr_cli.commands.compare.Comparison.measure`), and the driver writes the same files as
:func:`psdr_cli.commands.compare.run_comparison`.

Resources: a task asks for ``num_gpus: 1`` on CUDA (``variant: cuda_*``, or ``auto`` on a cluster
that has GPUs) and ``RayOptions.cpus`` CPUs otherwise; Dr.Jit's thread pool in the task is limited
to that many threads, so tasks do not oversubscribe a node. Without an address, a local Ray
instance is started (and shut down at the end); ``auto``, ``ray://host:port`` or ``host:port``
join an existing cluster.

Files reach the run folders in one of two ways (``RayOptions.files``):

``shared``  the workers write into the run folders themselves (a filesystem shared with the
            driver, e.g. NFS, or a local instance): exactly the sequential code path.
``copy``    a worker runs in a temporary folder of its own node, seeded with the run folder's
            resume set (``state.npz``, ``log.csv``, ``run.json``, ``targets/``; a fresh start: only
            ``targets/``) and sends the folder's new and changed files to the driver every
            ``sync_seconds`` and at the end,
            through a small actor (:class:`Hub`), and all of them with its result; the driver,
            the only writer of the run folders, writes them atomically (``state.npz`` last, so a saved state never runs
            ahead of its log); a fresh start moves a run it finds aside (:func:`psdr_cli.run_folder.layout.keep_previous_run`).

``auto`` is ``shared`` for a local instance and ``copy`` when joining a cluster.

A task whose worker (or node) dies is submitted again (``RayOptions.retries`` times) and
resumes from the run's last saved state (shared: ``state.npz`` in the run folder; copy: the
state last sent to the driver); resuming reproduces an uninterrupted run's losses (``docs/optimize.md``). Every run
has its own folder and exactly one task writes it at a time (a retry starts only once its failed
attempt is gone); files are written atomically. Progress events (start, iteration and loss,
warnings) go through the same actor to the driver, which shows one line per run.

Ray is an optional dependency (``pip install 'psdr[ray]'``), imported only on this code path.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
import time
from contextlib import ExitStack
from dataclasses import dataclass, replace
from pathlib import Path

from . import compare as comparison
from ..config.experiment_file import Experiment
from ..errors import PsdrError
from ..run_folder.layout import RunFiles, clear_run, keep_previous_run, lock_run
from ..run_folder.variant_folders import variant_experiments
from ..support import backend, fileio
from .optimize import loop_guiding_line, optimize

INSTALL = "pip install 'psdr[ray]'"
#: Files a copy-mode task needs to continue a run (everything else in a run folder is output only).
RESUME_SET = ("state.npz", "log.csv", "run.json", "targets/")
_ADDRESS = re.compile(r"^(auto|local|ray://\S+|[\w.-]+:\d+)$")


@dataclass
class RayOptions:
    """How a sweep uses Ray (the CLI's ``--ray [ADDRESS]``, ``--ray-cpus``, ``--ray-files``)."""
    address: str | None = None      # None or "local": start a local instance; "auto", "ray://host:port", "host:port": join
    cpus: int = 1                   # CPUs per task (and Dr.Jit threads) on the LLVM backend
    gpus: float | None = None       # GPUs per task; None: 1 on CUDA, 0 otherwise
    files: str = "auto"             # shared | copy | auto (see the module docstring)
    retries: int = 3                # resubmissions of a task whose worker died
    sync_seconds: float = 30.0      # copy mode: how often a task sends its new files to the driver
    local_cpus: int | None = None   # CPUs of a local instance (default: all of the machine)

    def __post_init__(self):
        if self.address is not None and not _ADDRESS.match(self.address):
            raise PsdrError(f"--ray: expected no value, 'auto', 'ray://HOST:PORT' or 'HOST:PORT', got '{self.address}'")
        if self.files not in ("auto", "shared", "copy"):
            raise PsdrError(f"--ray-files: expected shared, copy or auto, got '{self.files}'")
        if self.cpus < 1:
            raise PsdrError(f"--ray-cpus: expected a positive number, got {self.cpus}")

    @staticmethod
    def is_address(value: str) -> bool:
        """Whether a word after ``--ray`` is its address (not an option or a file)."""
        return bool(_ADDRESS.match(value))

    @property
    def local(self) -> bool:
        return self.address in (None, "local")

    @property
    def copy(self) -> bool:
        return self.files == "copy" or (self.files == "auto" and not self.local)


def import_ray():
    """The ``ray`` module, or a one-line error naming the install command."""
    try:
        # Ray is an optional, heavy dependency (``psdr[ray]``): deliberately imported only here,
        # on the --ray code path, never when the package is imported.
        import ray
    except ImportError:
        raise PsdrError(f"--ray: Ray is not installed; install it with: {INSTALL}") from None
    return ray


# --------------------------------------------------------------------------------------------
# The actor between tasks and the driver
# --------------------------------------------------------------------------------------------
class Hub:
    """Progress events and files from the tasks to the driver (a Ray actor the driver drains while
    it waits). Tasks only ever send to it, never wait on it: a task blocked in ``ray.get`` gives
    its CPUs back to Ray, which would then start more tasks than the node has cores."""

    def __init__(self):
        self.events, self.files = [], []

    def event(self, label, kind, *args):
        self.events.append((label, kind, args))

    def push(self, label, attempt: int, seq: int, fresh: bool, files: dict):
        self.files.append((label, attempt, seq, fresh, files))

    def drain(self):
        events, files = self.events, self.files
        self.events, self.files = [], []
        return events, files


def read_folder(root: Path, prefixes=None) -> dict:
    """{relative path: bytes} of the files under ``root`` (optionally only those under ``prefixes``),
    skipping the hidden temporary files of atomic writes."""
    out = {}
    if root.is_dir():
        for p in sorted(root.rglob("*")):
            rel = p.relative_to(root).as_posix()
            if p.is_file() and not any(part.startswith(".") for part in p.relative_to(root).parts) \
                    and (prefixes is None or rel.startswith(tuple(prefixes))):
                out[rel] = p.read_bytes()
    return out


def write_files(root: Path, fresh: bool, files: dict):
    """Driver side of copy mode: a fresh start clears the run as the worker did, then every file is
    written atomically, ``state.npz`` last."""
    if fresh:
        clear_run(RunFiles(root))
    for rel in sorted(files, key=lambda r: r == "state.npz"):
        with fileio.atomic_path(root / rel) as tmp:
            tmp.write_bytes(files[rel])


# --------------------------------------------------------------------------------------------
# Inside a task
# --------------------------------------------------------------------------------------------
def limit_threads(threads: int | None, variant: str | None):
    """Dr.Jit's CPU thread pool sized to the task's CPUs; ``variant`` pins the backend (a task
    without a GPU must not pick CUDA under ``variant: auto``)."""
    if variant:
        os.environ["PSDR_VARIANT"] = variant
    if threads:
        os.environ["DRJIT_NUM_THREADS"] = str(threads)
        import drjit as dr  # third-party; psdr_cli (imported with this module) configured Dr.Jit first
        dr.set_thread_count(threads)


class TaskProgress:
    """The ``progress`` object :func:`optimize` gets inside a task: events to the hub and, in copy
    mode, the run folder's new files every ``sync_seconds`` (called after each saved iteration)."""

    def __init__(self, hub, label, attempt: int, folder: Path | None, sync_seconds: float):
        self.hub, self.label, self.attempt, self.folder, self.sync_seconds = hub, label, attempt, folder, sync_seconds
        self.seq, self.fresh, self.last = 0, False, time.monotonic()
        self.initial = self.seen = self.scan() if folder is not None else {}

    def scan(self) -> dict:
        return {p: (p.stat().st_size, p.stat().st_mtime_ns) for p in self.folder.rglob("*")
                if p.is_file() and not p.name.startswith(".")}

    def changed(self, since: dict) -> tuple[dict, dict]:
        now = self.scan()
        return now, {p.relative_to(self.folder).as_posix(): p.read_bytes() for p, sig in now.items()
                     if since.get(p) != sig}

    def sync(self):
        """Send the files that are new or changed since the last sync (without waiting)."""
        if self.folder is None:
            return
        self.seen, files = self.changed(self.seen)
        self.seq += 1   # only the first batch of a fresh run clears the driver's run folder
        self.hub.push.remote(self.label, self.attempt, self.seq, self.fresh and self.seq == 1, files)
        self.last = time.monotonic()

    def final(self) -> tuple[int, bool, dict]:
        """(sequence number, fresh, every file new or changed since the task started): the
        task's return carries it, so a sync still on its way may be dropped."""
        return self.seq + 1, self.fresh, self.changed(self.initial)[1]

    def start(self, total: int, done: int = 0):
        self.hub.event.remote(self.label, "start", total, done)
        if self.folder is not None:
            self.fresh = done == 0          # the driver moves a run aside, or clears a dead attempt's files
            self.sync()

    def advance(self, n: int, loss: float | None = None):
        self.hub.event.remote(self.label, "advance", n, loss)
        if time.monotonic() - self.last >= self.sync_seconds:
            self.sync()

    def warn(self, message: str):
        self.hub.event.remote(self.label, "warn", message)


@dataclass
class RunTask:
    """One submission of a sweep's run: its label, its attempt (0 first; a later one resumes),
    the iterations (None: ``optimize.iterations``), whether it resumes and, in copy mode, the run
    folder's files it starts from (``snapshot``; None: shared mode)."""
    label: str | None
    attempt: int
    iterations: int | None
    resume: bool
    snapshot: dict | None


@dataclass
class TaskPlace:
    """Where a task runs and reports: the hub its events and files go to, how often it sends its
    files (copy mode), its Dr.Jit threads and the variant pinned in it."""
    hub: object
    sync_seconds: float
    threads: int | None
    variant: str | None

    def progress(self, task: RunTask, folder: Path | None) -> "TaskProgress":
        return TaskProgress(self.hub, task.label, task.attempt, folder, self.sync_seconds)


def optimize_task(run: Experiment, task: RunTask, place: TaskPlace):
    """One run of a sweep (a Ray task): :func:`optimize` on the run. With ``task.snapshot`` (copy
    mode: the run folder's resume set) the task runs in a temporary folder and returns
    (result, (seq, fresh, files)); shared mode (None): returns (result, None)."""
    limit_threads(place.threads, place.variant)
    backend.activate(run)  # a worker process: the run was loaded in the driver
    if task.snapshot is None:
        progress = place.progress(task, None)
        return optimize(run, iterations=task.iterations, resume=task.resume, progress=progress,
                        warn=progress.warn), None
    target = run.run_dir
    tmp = Path(tempfile.mkdtemp(prefix="psdr-ray-"))
    try:
        local = replace(run, output=tmp)
        for rel, data in task.snapshot.items():
            path = local.run_dir / rel
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
        local.run_dir.mkdir(parents=True, exist_ok=True)
        progress = place.progress(task, local.run_dir)
        result = optimize(local, iterations=task.iterations, resume=task.resume, progress=progress,
                          warn=progress.warn)
        files = RunFiles(local.run_dir)
        if files.summary.exists():  # the summary names the final mesh where the driver will have it
            info = json.loads(files.summary.read_text())
            info["final"] = str(RunFiles(target).final)
            fileio.write_json(files.summary, info)
        move = lambda p: target / Path(p).relative_to(local.run_dir)  # noqa: E731
        return replace(result, folder=target, final=move(result.final) if result.final else None,
                       checkpoints=[move(p) for p in result.checkpoints]), progress.final()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def reference_task(exp: Experiment, threads, variant):
    """The comparison's reference image (a Ray task): (image, its relMSE, seconds)."""
    limit_threads(threads, variant)
    comparison.check_comparison(exp)
    backend.activate(exp)
    return comparison.Comparison(exp, exp.compare.terms, exp.compare.view).reference(exp.compare.reference_passes)


def measure_task(exp: Experiment, v, reference, threads, variant):
    """One variant of a comparison (a Ray task): its :class:`psdr_cli.commands.compare.Row`."""
    limit_threads(threads, variant)
    backend.activate(exp)
    ref, noise, _ = reference
    cfg = exp.compare
    return comparison.Comparison(exp, cfg.terms, cfg.view).measure(v, ref, noise, cfg.budget_seconds, cfg.trials)


# --------------------------------------------------------------------------------------------
# The driver
# --------------------------------------------------------------------------------------------
class Session:
    """Ray started (locally) or joined for one sweep; shut down at the end if we started it."""

    def __init__(self, opts: RayOptions):
        self.ray, self.opts, self.started = import_ray(), opts, False

    def __enter__(self):
        ray = self.ray
        if not ray.is_initialized():
            env = {k: os.environ[k] for k in ("PSDR_VARIANT", "DRJIT_LIBLLVM_PATH", "DRJIT_CACHE_DIR")
                   if k in os.environ and (k == "PSDR_VARIANT" or self.opts.local)}
            kwargs = dict(runtime_env={"env_vars": env}, logging_level="WARNING", log_to_driver=True)
            if self.opts.local:
                ray.init(num_cpus=self.opts.local_cpus, include_dashboard=False, **kwargs)
            else:
                try:
                    ray.init(address=self.opts.address, **kwargs)
                except Exception as exc:  # noqa: BLE001 - no cluster there
                    first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                    raise PsdrError(f"--ray {self.opts.address}: cannot join the Ray cluster ({first})") from None
            self.started = True
        return self

    def __exit__(self, *exc):
        if self.started:
            self.ray.shutdown()

    def resources(self, exp: Experiment) -> tuple[dict, str | None, int | None]:
        """(resource request, variant pinned in the task, Dr.Jit threads) of a task of ``exp``."""
        variant = os.environ.get("PSDR_VARIANT", exp.variant) or "auto"
        gpus = self.opts.gpus
        if gpus is None:
            if variant.startswith("cuda"):
                gpus = 1
            elif variant == "auto":
                gpus = 1 if self.ray.cluster_resources().get("GPU", 0) >= 1 else 0
            else:
                gpus = 0
        if gpus:
            return {"num_cpus": 1, "num_gpus": gpus}, ("cuda_ad_rgb" if variant == "auto" else None), None
        return {"num_cpus": self.opts.cpus}, ("llvm_ad_rgb" if variant == "auto" else None), self.opts.cpus


def task_error(label, exc) -> PsdrError:
    """One line for a failed task (a PsdrError raised in the task keeps its message)."""
    cause = getattr(exc, "cause", None) or exc
    if isinstance(cause, PsdrError):
        return PsdrError(f"{label}: {cause}" if label else str(cause))
    first = str(cause).splitlines()[0] if str(cause) else ""
    return PsdrError(f"{label or 'run'}: {type(cause).__name__}: {first}")


def wait_all(ray, hub, pending: dict, on_event=None, on_files=None):
    """Yield (label, result or exception) as the tasks end, forwarding the hub's events and files."""
    def flush():
        if hub is None:
            return
        events, files = ray.get(hub.drain.remote())
        for label, kind, args in events:
            on_event(label, kind, args)
        for label, *batch in files:
            on_files(label, *batch)
    try:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1, timeout=0.5)
            flush()
            for ref in done:
                label = pending.pop(ref)
                try:
                    yield label, ray.get(ref)
                except Exception as exc:  # noqa: BLE001 - the caller decides: retry or report
                    yield label, exc
        flush()
    finally:
        for ref in pending:  # interrupted: the runs' saved states stay; --resume continues them
            ray.cancel(ref, force=True)


def died(ray, exc) -> bool:
    """Whether a task failed because its worker or node died (retried) rather than raised."""
    e = ray.exceptions
    kinds = tuple(getattr(e, n) for n in ("WorkerCrashedError", "NodeDiedError", "OutOfMemoryError",
                                          "LocalRayletDiedError") if hasattr(e, n))
    return isinstance(exc, kinds)


class Sweep:
    """The driver's side of an optimisation sweep: the runs by label, their attempts, the files
    applied from each, the tasks pending, the progress objects and where warnings go."""

    def __init__(self, session: Session, runs: dict, iterations: int | None, progress, warn):
        self.session, self.opts, self.runs, self.iterations, self.warn = session, session.opts, runs, iterations, warn
        ray = session.ray
        self.hub = ray.remote(num_cpus=0)(Hub).remote()
        self.task = ray.remote(max_retries=0)(optimize_task)   # retried below, resuming
        self.attempts, self.applied, self.pending, self.kept = {}, {}, {}, set()
        self.bars = {label: progress(label) if progress else None for label in runs}

    def submit(self, label, resume_run: bool):
        """Submit (again) the task of run ``label``; copy mode sends the files it resumes from (a
        fresh start needs only the cached targets: the driver moves a run it finds aside)."""
        run = self.runs[label]
        self.attempts[label] = self.attempts.get(label, -1) + 1
        self.applied[label] = 0
        request, variant, threads = self.session.resources(run)
        snapshot = read_folder(run.run_dir, RESUME_SET if resume_run else ("targets/",)) if self.opts.copy else None
        task = RunTask(label, self.attempts[label], self.iterations, resume_run, snapshot)
        place = TaskPlace(self.hub, self.opts.sync_seconds, threads, variant)
        self.pending[self.task.options(**request).remote(run, task, place)] = label

    def on_files(self, label, attempt, seq, fresh, files):
        """Files of a task's sync, written into its run folder (late syncs of a finished or dead
        attempt are dropped)."""
        if attempt == self.attempts[label] and seq > self.applied[label]:
            if fresh and label not in self.kept:  # a fresh start moves a run it finds aside, as optimize() does
                keep_previous_run(RunFiles(self.runs[label].run_dir), self.warn)
                self.kept.add(label)
            write_files(self.runs[label].run_dir, fresh, files)
            self.applied[label] = seq

    def on_event(self, label, kind, args):
        """A task's warning, or its progress (``start``, ``advance``) on its progress object."""
        if kind == "warn":
            self.warn(f"{label}: {args[0]}" if label else args[0])
        elif self.bars[label] is not None:
            getattr(self.bars[label], kind)(*args)

    def retried(self, label, outcome: Exception) -> bool:
        """Whether the failed task of ``label`` is submitted again (its worker died, retries left)."""
        if died(self.session.ray, outcome) and self.attempts[label] < self.opts.retries:
            self.warn(f"{label or 'run'}: the task died ({type(outcome).__name__}); attempt "
                      f"{self.attempts[label] + 2} resumes from the saved state")
            self.submit(label, True)
            return True
        return False


def optimize_sweep(exp: Experiment, labels=None, iterations: int | None = None, resume: bool = False,
                   opts: RayOptions | None = None, *, progress=None, warn=print, report=None):
    """:func:`psdr_cli.commands.optimize.optimize_variants` on Ray: every run one task; yields
    (label, OptimizeResult) as each ends (in the order they end); raises the first failure once
    every run has ended. A task whose worker died is submitted again (``opts.retries`` times),
    continuing from the run's saved state.

    ``progress(label)``: optional factory of an object with ``start(total, done)`` and
    ``advance(n, loss)`` per run (one progress line per run); ``report``: one line per run before
    the tasks start, what guides its boundary terms in the loop."""
    opts = opts or RayOptions()
    if exp.optimize is None:
        raise PsdrError(f"{exp.file}: optimize: missing (expected at least {{object: NAME}})")
    runs = dict(variant_experiments(exp, labels))
    if report:  # before any task is submitted: the progress rows are not drawn yet
        for label, run in runs.items():
            report(loop_guiding_line(label, run))
    with Session(opts) as session, ExitStack() as locks:
        if opts.copy:  # the driver is the one writer of every run folder (shared mode: each task's optimize locks)
            for run in runs.values():
                locks.enter_context(lock_run(RunFiles(run.run_dir)))
        sweep = Sweep(session, runs, iterations, progress, warn)
        for label in runs:
            sweep.submit(label, resume)
        failure = None
        for label, outcome in wait_all(session.ray, sweep.hub, sweep.pending, sweep.on_event, sweep.on_files):
            if isinstance(outcome, Exception):
                if sweep.retried(label, outcome):
                    continue
                error = task_error(label, outcome)
                warn(f"{label or 'run'} failed: {error}")
                failure = failure or error
                continue
            result, final = outcome
            if final is not None:
                sweep.on_files(label, sweep.attempts[label], *final)
            yield label, result
        if failure:
            raise failure


def compare_sweep(exp: Experiment, out: Path | None = None, opts: RayOptions | None = None, progress=None):
    """:func:`psdr_cli.commands.compare.run_comparison` on Ray: the reference one task, then every variant
    one task (in parallel); the driver writes the same files. ``progress(label)`` as in
    :func:`optimize_sweep`. Equal-time budgets then hold per task (its CPUs or GPU), not for the
    whole machine: relMSE values of a variant are comparable within one sweep."""
    opts = opts or RayOptions()
    comparison.check_comparison(exp)
    cfg = exp.compare
    with Session(opts) as session:
        ray = session.ray
        request, variant, threads = session.resources(exp)
        ref = ray.remote(reference_task).options(**request, max_retries=opts.retries).remote(exp, threads, variant)
        measure = ray.remote(measure_task).options(**request, max_retries=opts.retries)
        pending = {ref: "reference"}
        pending.update({measure.remote(exp, v, ref, threads, variant): v.label for v in cfg.variants})
        bars = {label: progress(label) if progress else None for label in pending.values()}
        for bar in bars.values():
            if bar is not None:
                bar.start(1, 0)
        results = {}
        for label, result in wait_all(ray, None, pending):
            if isinstance(result, Exception):
                raise task_error(label, result)
            results[label] = result
            if bars[label] is not None:
                bars[label].advance(1, result.rel_mse if label != "reference" else None)
    ref_image, noise, ref_seconds = results["reference"]
    folder = exp.command_dir("compare", out)
    rows = [results[v.label] for v in cfg.variants]
    return comparison.write_comparison(exp, folder, ref_image, noise, ref_seconds, rows)

