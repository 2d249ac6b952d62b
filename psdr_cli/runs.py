"""The run-folder contract of ``psdr optimize``: what a run folder holds and how it is read.

A run of an experiment lives in ``<output>/<name>/`` (with ``optimize.variants``: one folder per
variant, ``<output>/<name>/<label>/``) and holds

    run.json            fingerprint of the experiment the run belongs to (:func:`run_record`)
    state.npz           everything needed to continue (written atomically after every iteration)
    log.csv             one row per completed iteration (:data:`LOG_FIELDS`)
    checkpoints/        iter_NNNN.ply every ``checkpoint_every`` iterations (iter_0000: the start)
    previews/           target | current | |difference| strips of the preview views
    targets/            the target images (cached by a content hash)
    reference.ply       the ground truth the targets were rendered from (mesh targets only)
    final.ply, optimize.json, loss.png, chamfer.png   once the run has finished

Every file is written atomically (:func:`psdr_cli.fileio.atomic_path`) except ``log.csv``, which
is appended to and rewritten (atomically) up to the last saved iteration on resume; it is read
tolerantly (:func:`read_log`: a torn or garbage tail is ignored with a warning).

While ``psdr optimize`` writes a run folder it holds an exclusive lock (:func:`lock_run`,
``fcntl.flock`` on ``.<name>.lock`` next to the folder, released by the OS when the process
ends); a second process is refused with the holder's PID.
"""
from __future__ import annotations

import csv
import fcntl
import hashlib
import io
import json
import os
import re
import shutil
import time
import warnings
from contextlib import contextmanager
from dataclasses import MISSING, dataclass, field, fields, is_dataclass, replace
from pathlib import Path

import numpy as np

from . import fileio, plots
from .config import COMMAND_FOLDERS, Experiment, with_estimator
from .errors import PsdrError, PsdrWarning
from .meshes import write_ply

#: Names of the checkpoints in ``checkpoints/`` (other files there are not checkpoints).
CHECKPOINT_NAME = re.compile(r"iter_(\d+)\.ply")
LOG_FIELDS = ("iteration", "loss", "vertices", "seconds_guiding", "seconds_rendering", "seconds_post",
              "seconds_total", "skipped", "guide_bytes")


class RunFiles:
    """Paths inside a run folder ``<output>/<name>/``."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.checkpoints = self.root / "checkpoints"
        self.previews = self.root / "previews"
        self.targets = self.root / "targets"
        self.state = self.root / "state.npz"
        self.log = self.root / "log.csv"
        self.reference = self.root / "reference.ply"
        self.final = self.root / "final.ply"
        self.summary = self.root / "optimize.json"
        self.run = self.root / "run.json"          # fingerprint of the experiment the run belongs to
        self.albedo = self.root / "albedo.exr"      # the recovered texture (optimize.albedo.texture)
        self.envmap = self.root / "envmap.exr"      # the recovered environment map (optimize.envmap)

    def checkpoint(self, iteration: int) -> Path:
        return self.checkpoints / f"iter_{iteration:04d}.ply"

    def material(self, name: str) -> Path:
        """The recovered texture of ``optimize.material.NAME`` (grey linear EXR)."""
        return self.root / f"{name}.exr"

    def check_files(self):
        """Refuse a run folder whose state, log, summary, meshes or plots are not regular files
        (a folder, a device, a FIFO: :func:`psdr_cli.fileio.check_output_file`), before any of
        them is read (a FIFO would block) or the run's work is done."""
        for path in (self.state, self.log, self.reference, self.final, self.summary, self.run,
                     self.root / "loss.png", self.albedo, self.envmap):
            fileio.check_output_file(path)


@contextmanager
def lock_run(files: RunFiles):
    """Hold the exclusive lock of a run folder for the duration of the block.

    The lock is ``fcntl.flock`` on ``<parent>/.<name>.lock`` (outside the folder, so that the folder
    itself can be moved aside), which holds the PID of its holder; the OS releases it when the
    process dies, so a killed run never leaves a stale lock. Holding it, the temporaries that a
    killed writer left in the folder are deleted (the files they were to replace are intact)."""
    path = files.root.parent / f".{files.root.name}.lock"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError as exc:
        raise PsdrError(f"{path}: cannot create the run's lock file ({fileio.describe_os_error(exc)})") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            raise PsdrError(f"{files.root}: another psdr process (PID {holder}) is writing this run; "
                            f"wait for it to end or stop it") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        fileio.remove_temporaries(files.root)  # a writer killed mid-write (kill -9) leaves its temporary
        yield
    finally:
        os.close(fd)  # releases the lock (the file stays: unlinking it would race with a waiting process)


def move_aside(files: RunFiles) -> Path:
    """Rename a run folder to ``<name>.previous-<time>`` (kept, not deleted); returns the new path."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    target = files.root.with_name(f"{files.root.name}.previous-{stamp}")
    n = 1
    while target.exists():
        n += 1
        target = files.root.with_name(f"{files.root.name}.previous-{stamp}-{n}")
    try:
        files.root.rename(target)
    except OSError as exc:
        raise PsdrError(f"{files.root}: cannot move the previous run aside ({fileio.describe_os_error(exc)})") from None
    return target


#: Entries of a run folder that are not a run's results: the cached targets (keyed by
#: content), the reference they were rendered from, the lock's record and other commands' outputs.
NOT_RESULTS = ("targets", "reference.ply", "run.json", *COMMAND_FOLDERS)


def has_results(files: RunFiles) -> bool:
    """Whether the folder holds anything a run wrote besides :data:`NOT_RESULTS` (a state, log,
    checkpoint, preview, plot, texture, ...)."""
    return files.root.is_dir() and any(p.name not in NOT_RESULTS for p in files.root.iterdir())


def clear_run(files: RunFiles):
    """Remove what a dead attempt of a fresh run wrote (everything but :data:`NOT_RESULTS`): a
    retried task that starts afresh must not leave the dead attempt's later checkpoints behind.
    Only for a folder whose previous run :func:`keep_previous_run` has already moved aside."""
    for p in files.root.iterdir() if files.root.is_dir() else ():
        if p.name in NOT_RESULTS:
            continue
        if p.is_dir():
            shutil.rmtree(p)
        else:
            p.unlink()


def keep_previous_run(files: RunFiles, warn) -> None:
    """Before a fresh start: a run found in the folder is moved aside (:func:`move_aside`), never
    deleted. Its targets are copied back (a cache keyed by content, :func:`psdr_cli.targets.target_key`)
    and the other commands' output folders are moved back (they are not the run's)."""
    if not has_results(files):
        return
    kept = move_aside(files)
    try:
        if (kept / "targets").is_dir():
            shutil.copytree(kept / "targets", files.targets)
        for name in COMMAND_FOLDERS:
            if (kept / name).is_dir():
                files.root.mkdir(parents=True, exist_ok=True)
                (kept / name).rename(files.root / name)
    except OSError as exc:
        raise PsdrError(f"{files.root}: the previous run is kept in {kept}, but its targets or command outputs "
                        f"could not be brought back ({fileio.describe_os_error(exc)})") from None
    warn(f"{files.root} held a previous run; it is kept in {kept}")


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


def write_mesh(path: Path, V, F):
    """PLY written atomically (opens in MeshLab and Blender); refuses NaN or infinite vertices."""
    fileio.check_finite(path, V, "mesh")
    with fileio.atomic_path(path) as tmp:
        write_ply(tmp, V, F)


# --------------------------------------------------------------------------------------------
# Fingerprint
# --------------------------------------------------------------------------------------------
#: Version of :func:`run_fingerprint`, recorded in run.json next to the fingerprint.
FINGERPRINT_VERSION = 2
#: Optimize keys that only extend or observe a run: changing them continues the same run.
OBSERVING_KEYS = ("iterations", "seconds", "checkpoint_every", "preview_views", "variants")
#: Estimator keys read only by the Mitsuba engine, and only by the psdr engine.
MITSUBA_ONLY_KEYS = ("mitsuba_integrator", "mitsuba_spp", "mitsuba_shadows")
PSDR_ONLY_KEYS = ("primary_sampling",)


def run_fingerprint(exp: Experiment) -> str:
    """Hash of what a run's result depends on: the scene, estimator and optimize sections and the
    seed, written by :func:`non_default` (a key at its default is left out, so a key added with a
    default changes no fingerprint), without the optimize keys that only extend or observe a run
    (:data:`OBSERVING_KEYS`) and the estimator keys the run's engine does not read, with paths
    relative to the experiment's folder. ``--resume`` continues a run only while this is
    unchanged. The contents of mesh and image files are not part of it."""
    est = non_default(exp.estimator)
    for key in MITSUBA_ONLY_KEYS if exp.estimator.engine == "psdr" else PSDR_ONLY_KEYS:
        est.pop(key, None)
    opt = non_default(exp.optimize)
    for key in OBSERVING_KEYS:
        opt.pop(key, None)
    return _digest(exp, (scene_identity(non_default(exp.scene)), est, opt))


def scene_identity(d: dict) -> dict:
    """A scene's dict (``asdict`` or :func:`non_default`) with ``mitsuba.resolved: true``, the flag
    an XML scene's source carried once read, before experiments were loaded whole: fingerprints
    and cached targets of runs saved then still match."""
    if d.get("mitsuba"):
        d["mitsuba"] = {**d["mitsuba"], "resolved": True}
    return d


def _digest(exp: Experiment, parts) -> str:
    h = hashlib.sha256()
    for part in parts:
        text = json.dumps(part, default=str, sort_keys=True)
        h.update(text.replace(str(exp.base_dir), "<experiment folder>").encode())  # the checkout may move
    h.update(str(exp.seed).encode())
    return h.hexdigest()[:16]


def non_default(value):
    """A config dataclass as a dict without the fields whose value equals the field's default,
    recursively (lists, tuples and dicts of dataclasses included); other values as they are."""
    if is_dataclass(value) and not isinstance(value, type):
        return {f.name: non_default(getattr(value, f.name)) for f in fields(value)
                if not _is_default(f, getattr(value, f.name))}
    if isinstance(value, (list, tuple)):
        return [non_default(v) for v in value]
    if isinstance(value, dict):
        return {k: non_default(v) for k, v in value.items()}
    return value


def _is_default(f, value) -> bool:
    if f.default is not MISSING:
        default = f.default
    elif f.default_factory is not MISSING:
        default = f.default_factory()
    else:
        return False  # a required field
    return _canonical(value) == _canonical(default)


def _canonical(value) -> str:
    """JSON text of :func:`non_default` of a value (tuples and lists alike), so that arrays and
    nested dataclasses compare by what the fingerprint holds of them."""
    return json.dumps(non_default(value), default=str, sort_keys=True)


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


# --------------------------------------------------------------------------------------------
# Fingerprint version 1 (run.json without "fingerprint_version"): read only, kept unchanged so
# that such runs can be resumed. It hashes every field that existed in version 1 (V1_FIELDS);
# a field added since is hashed only when it differs from its default.
# --------------------------------------------------------------------------------------------
def fingerprint_v1(exp: Experiment) -> str:
    """Version-1 fingerprint: scene, estimator, seed and the optimize section except iterations,
    seconds, checkpoint_every, preview_views and variants (:func:`estimator_identity_v1`,
    :func:`optimize_identity_v1`), paths relative to the experiment's folder."""
    opt = replace(exp.optimize, iterations=0, seconds=None, checkpoint_every=0, preview_views=(), variants=())
    return _digest(exp, (scene_identity(_asdict_v1(exp.scene)), estimator_identity_v1(exp.estimator),
                         optimize_identity_v1(opt)))


def optimize_identity_v1(opt) -> dict:
    """Version-1 optimize keys: a single λ as its number, no ``downsample`` when every stage
    renders at full resolution."""
    d = _asdict_v1(opt)
    if len(opt.lambda_) == 1:
        d["lambda_"] = opt.lambda_[0]
    if all(k == 1 for k in opt.downsample):
        d.pop("downsample")
    return d


def estimator_identity_v1(est) -> dict:
    """Version-1 estimator keys: without the engine keys with ``engine: psdr``, without
    ``primary_sampling`` with ``engine: mitsuba`` or ``primary_sampling: length``."""
    d = _asdict_v1(est)
    if est.engine == "psdr":
        for key in ("engine", "mitsuba_integrator", "mitsuba_spp", "mitsuba_shadows"):
            d.pop(key)
    if est.engine == "mitsuba" or est.primary_sampling == "length":
        d.pop("primary_sampling")
    return d


def _asdict_v1(value):
    """``dataclasses.asdict`` without the fields that are not in :data:`V1_FIELDS` and hold their
    default."""
    if is_dataclass(value) and not isinstance(value, type):
        known = V1_FIELDS.get(type(value).__name__, ())
        return {f.name: _asdict_v1(getattr(value, f.name)) for f in fields(value)
                if f.name in known or not _is_default(f, getattr(value, f.name))}
    if isinstance(value, (list, tuple)):
        return type(value)(_asdict_v1(v) for v in value)
    if isinstance(value, dict):
        return {k: _asdict_v1(v) for k, v in value.items()}
    return value


#: The fields of the config dataclasses when version 1 was current.
V1_FIELDS = {
    "SceneConfig": ("width", "height", "max_depth", "cameras", "emitters", "objects", "mitsuba"),
    "CameraConfig": ("origin", "target", "up", "fov"),
    "EmitterConfig": ("type", "key", "radiance", "center", "normal", "size", "file", "scale", "rotate_deg",
                      "sun_direction", "turbidity", "albedo", "sun_scale", "sky_scale"),
    "ObjectConfig": ("name", "mesh", "key", "transform", "bsdf", "edges", "smooth", "bsdf_given", "parts"),
    "MeshSpec": ("key", "file", "shape", "params", "repair", "part", "split"),
    "TransformConfig": ("translate", "rotate_axis", "rotate_deg", "scale"),
    "BsdfConfig": ("type", "params"),
    "BitmapConfig": ("file", "filter_type", "wrap_mode", "raw", "data"),
    "MitsubaSource": ("file", "params", "film", "edges", "up", "up_given", "cameras_given", "max_depth_given",
                      "digest", "resolved"),
    "EstimatorConfig": ("spp", "primary_spp", "boundary_spp", "terms", "sampling", "guiding", "passes",
                        "guide_epsilon", "edge_sort", "primary_sampling", "engine", "mitsuba_integrator",
                        "mitsuba_spp", "mitsuba_shadows", "chains", "grid", "kdtree"),
    "ChainConfig": ("max_turn", "max_length"),
    "GridConfig": ("resolution", "samples_per_cell"),
    "KdTreeConfig": ("samples_per_node", "initial_samples", "refine_ratio", "interval_share", "technique_share",
                     "threshold", "max_depth", "max_leaves"),
    "OptimizeConfig": ("object", "target_images", "target_mesh", "target_spp", "init", "init_transform", "remesh",
                       "iterations", "batch_size", "learning_rate", "learning_rate_final", "lambda_", "downsample",
                       "guide_every", "adjoint_spp", "checkpoint_every", "preview_views", "albedo", "albedo_init",
                       "albedo_learning_rate", "albedo_texture", "envmap_rotation", "envmap_axis",
                       "envmap_init_deg", "envmap_learning_rate", "seconds", "variants", "target_seed"),
    "RemeshConfig": ("method", "initial", "at", "vertices"),
    "Variant": ("label", "guiding", "sampling", "edge_sort", "seed", "passes", "engine"),
}


# --------------------------------------------------------------------------------------------
# log.csv
# --------------------------------------------------------------------------------------------
def read_log(path: Path, before: int | None = None) -> list:
    """Rows of ``log.csv`` (for iterations < ``before``: later rows belong to unsaved work).

    The log is appended to in place, so a killed process or a full disk can leave a torn last
    row or garbage (NUL bytes) at its end. Rows are read up to the first one that is not complete:
    every field present and numeric, iterations consecutive from 0, the line ended by a newline.
    The rest is ignored with a :class:`PsdrWarning` naming the line (``psdr optimize --resume``
    then rewrites the log without it)."""
    if not path.exists():
        return []
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise PsdrError(f"{path}: cannot read ({fileio.describe_os_error(exc)})") from None
    lines = raw.decode("utf-8", errors="replace").splitlines(keepends=True)
    rows = []
    header = next(csv.reader(lines[:1]), None)
    if header != list(LOG_FIELDS):
        if raw.strip(b"\x00 \r\n"):
            warnings.warn(f"{path}: the header is damaged; the log is ignored", PsdrWarning, stacklevel=2)
        return []
    for number, line in enumerate(lines[1:], start=2):
        fields = next(csv.reader([line]), [])
        if not line.endswith("\n") or len(fields) != len(LOG_FIELDS) or not _complete(fields, len(rows)):
            warnings.warn(f"{path}: line {number} is torn or damaged; ignoring it and the "
                          f"{len(lines) - number} lines after it", PsdrWarning, stacklevel=2)
            break
        rows.append(dict(zip(LOG_FIELDS, fields)))
    return [r for r in rows if before is None or int(r["iteration"]) < before]


def _complete(fields: list, index: int) -> bool:
    """Whether a log row's fields parse (integer iteration ``index``, numbers elsewhere)."""
    try:
        if int(fields[0]) != index:
            return False
        for value in fields[1:]:
            float(value)
        return True
    except ValueError:
        return False


def write_log(path: Path, rows: list):
    """The whole log, atomically."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, LOG_FIELDS)
    w.writeheader()
    w.writerows(rows)
    with fileio.atomic_path(path) as tmp:
        Path(tmp).write_text(buf.getvalue())


def append_log(path: Path, row: dict):
    """One more row at the end of the log (flushed to the OS before returning)."""
    try:
        with open(path, "a", newline="") as f:
            csv.DictWriter(f, LOG_FIELDS).writerow(row)
    except OSError as exc:
        raise PsdrError(f"{path}: cannot write ({fileio.describe_os_error(exc)})") from None


# --------------------------------------------------------------------------------------------
# Reading finished runs
# --------------------------------------------------------------------------------------------
def run_checkpoints(folder: Path):
    """[(iteration, path)] of a run folder (initial shape, checkpoints, final)."""
    folder = Path(folder)
    found = sorted((int(p.stem[5:]), p) for p in RunFiles(folder).checkpoints.glob("iter_*.ply")
                   if CHECKPOINT_NAME.fullmatch(p.name))  # not iter_abc.ply, a copy's "iter_0010 (2).ply"
    if not found:
        raise PsdrError(f"{folder}: no checkpoints (expected checkpoints/iter_NNNN.ply from `psdr optimize`)")
    return found


def run_seconds(folder: Path) -> dict:
    """{iteration: optimisation seconds so far} from the run's log.csv (iteration i ends at i+1)."""
    return {int(r["iteration"]) + 1: float(r["seconds_total"]) for r in read_log(RunFiles(folder).log)}


def run_summary(folder: Path) -> dict:
    """Per-iteration time split and guide memory of a finished run (the columns of the paper's
    Table 2), from its log.csv and optimize.json:

        guiding / rendering / post-processing seconds = mean over the logged iterations,
        guide memory = the largest guide set built (bytes)."""
    files = RunFiles(folder)
    if not files.log.exists():
        raise PsdrError(f"{folder}: no log.csv (expected a `psdr optimize` run folder)")
    rows = read_log(files.log)
    if not rows:
        raise PsdrError(f"{files.log}: no iterations logged")
    mean = lambda key: float(np.mean([float(r[key]) for r in rows]))  # noqa: E731
    try:
        info = json.loads(files.summary.read_text())
    except (OSError, ValueError):
        info = {}
    if info.get("iterations") != len(rows):
        raise PsdrError(f"{folder}: the run is unfinished ({len(rows)} iterations logged, no final result); "
                        f"finish it with `psdr optimize --resume`")
    return {"iterations": len(rows), "seconds": float(rows[-1]["seconds_total"]),
            "seconds_guiding": mean("seconds_guiding"), "seconds_rendering": mean("seconds_rendering"),
            "seconds_post": mean("seconds_post"), "vertices": int(rows[-1]["vertices"]),
            "guide_bytes": max(int(r.get("guide_bytes") or 0) for r in rows), "views": info.get("views")}


# --------------------------------------------------------------------------------------------
# The saved state, checkpoints and previews, the loss plot
# --------------------------------------------------------------------------------------------
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


def write_checkpoint(files: RunFiles, iteration: int, V, F, texture=None, previews: dict | None = None,
                     zoom: int = 1) -> Path:
    """checkpoints/iter_NNNN.ply; with ``texture`` (the recovered albedo texture, linear RGB)
    albedo.exr, albedo.png and its preview; per preview view {v: (target, current)} a target |
    current | |difference| strip with pixels enlarged ``zoom`` times (a downsampled stage's
    images at the film's size)."""
    path = files.checkpoint(iteration)
    write_mesh(path, V, F)
    if texture is not None:
        fileio.write_rgb_exr(files.albedo, texture, {"psdr.iteration": str(iteration)})
        fileio.write_preview(files.albedo.with_suffix(".png"), texture)
        fileio.write_preview(files.previews / f"iter_{iteration:04d}_albedo.png", texture)
    for v, images in (previews or {}).items():
        full = [np.repeat(np.repeat(image, zoom, axis=0), zoom, axis=1) for image in images]
        fileio.write_preview(files.previews / f"iter_{iteration:04d}_view_{v:03d}.png", strip(*full))
    return path


def strip(target, current, zoom: int = 3):
    """target | current | |difference| side by side, pixels enlarged ``zoom`` times, linear RGB."""
    gap = np.ones((target.shape[0], 2, 3))
    row = np.concatenate([target, gap, current, gap, np.abs(target - current)], axis=1)
    return np.repeat(np.repeat(row, zoom, axis=0), zoom, axis=1)


def plot_loss(files: RunFiles, rows: list):
    if not rows:
        return
    it = np.array([int(r["iteration"]) for r in rows])
    loss = np.array([float(r["loss"]) for r in rows])
    plots.lines(files.root / "loss.png", {"loss": (it, loss)}, "iteration",
                "loss (image L1, and any silhouette or prior terms)", "psdr optimize", logy=True)


def cached_target(path, key: str, shape: tuple):
    """The cached target image at ``path`` (in ``targets/``) if it can be trusted: it exists,
    reads back whole (not emptied or cut short by a full disk or a copy), was rendered for ``key``
    (:func:`psdr_cli.targets.target_key`), has the film's (height, width) and finite values; else
    None (the targets are rendered again). A missing file is not read (the EXR library would print
    its own error)."""
    if not Path(path).is_file():
        return None
    try:
        exr = fileio.read_exr(path)
        image = np.stack([exr[c] for c in "RGB"], -1).astype(np.float64)
    except Exception:  # noqa: BLE001 - missing, empty, truncated or not an EXR at all
        return None
    if exr["__header__"].get("psdr.target_key") != key or image.shape[:2] != shape or not np.isfinite(image).all():
        return None
    return image
