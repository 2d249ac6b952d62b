"""log.csv: one row per completed iteration, read tolerantly, and the loss plot drawn from it;
the time split of a finished run."""
from __future__ import annotations

import csv
import io
import json
import warnings
from pathlib import Path

import numpy as np

from ..errors import PsdrError, PsdrWarning
from ..support import fileio, plots
from .layout import RunFiles


LOG_FIELDS = ("iteration", "loss", "vertices", "seconds_guiding", "seconds_rendering", "seconds_post",
              "seconds_total", "skipped", "guide_bytes")


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



def plot_loss(files: RunFiles, rows: list, label: str):
    """loss.png: the logged loss per iteration (log scale), its axis labelled ``label`` (what the
    loss sums: :data:`psdr_cli.losses.registry.PLOT_LABEL`)."""
    if not rows:
        return
    it = np.array([int(r["iteration"]) for r in rows])
    loss = np.array([float(r["loss"]) for r in rows])
    plots.lines(files.root / "loss.png", {"loss": (it, loss)}, "iteration", label, "psdr optimize", logy=True)
