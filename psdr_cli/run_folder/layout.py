"""A run folder's layout (:class:`RunFiles`), its lock, and what becomes of a previous run
found in it (moved aside, never deleted)."""
from __future__ import annotations

import fcntl
import os
import shutil
import time
from contextlib import contextmanager
from pathlib import Path

from ..config.vocabularies import COMMAND_FOLDERS
from ..errors import PsdrError
from ..support import fileio


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
        (a folder, a device, a FIFO: :func:`psdr_cli.support.fileio.check_output_file`), before any of
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
    deleted. Its targets are copied back (a cache keyed by content, :func:`psdr_cli.target_sources.rendered_mesh.target_key`)
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
