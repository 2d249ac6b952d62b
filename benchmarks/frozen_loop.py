#!/usr/bin/env python
"""The optimisation loop as the user runs it, with the recorded part of its iterations
(``optimize.freeze: true``, psdr_cli/optimisation/frozen_batch.py) and without: ``psdr optimize`` of the demo's
experiment (``configs/reconstruct_bunny.yaml``, its initial shape, no remesh within the run) for
``--iterations`` iterations, frozen and traced alternated ``--rounds`` times, each run a fresh
process (the kernel cache warm after the first). Per run: the median and mean seconds per
iteration after the first (from the run's ``log.csv``), the first iteration's seconds (recording
and, cold, compiling) and the final loss. ``reference`` is the time of a fixed Python loop of 10⁷
steps before and after: compare machines through it.

    .venv/bin/python benchmarks/frozen_loop.py [--iterations 60] [--rounds 2] [--json FILE]
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import reference_loop_seconds  # noqa: E402

CONFIG = REPO / "configs" / "reconstruct_bunny.yaml"


def run(tmp: Path, freeze: bool, iterations: int, label: str) -> dict:
    cfg = yaml.safe_load(CONFIG.read_text())
    cfg["output"] = str(tmp / "runs")
    cfg["name"] = label
    cfg["optimize"].update(iterations=iterations, freeze=freeze, checkpoint_every=10 ** 6)
    cfg["optimize"]["remesh"] = {**cfg["optimize"]["remesh"], "at": [], "vertices": []}
    path = tmp / f"{label}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    proc = subprocess.run([sys.executable, "-m", "psdr_cli", "optimize", str(path)], cwd=REPO,
                          capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=os.pathsep.join(
                              [str(REPO)] + ([os.environ["PYTHONPATH"]] if os.environ.get("PYTHONPATH") else []))))
    if proc.returncode != 0:
        raise SystemExit(f"{label}: psdr optimize failed:\n{proc.stderr[-2000:]}")
    with open(tmp / "runs" / label / "log.csv") as f:
        rows = list(csv.DictReader(f))
    totals = [float(r["seconds_total"]) for r in rows]
    steps = [b - a for a, b in zip(totals, totals[1:])]
    return {"freeze": freeze, "first_s": totals[0], "median_s": statistics.median(steps),
            "mean_s": statistics.fmean(steps), "final_loss": float(rows[-1]["loss"]), "iterations": len(rows)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    out = {"reference_before": reference_loop_seconds(), "runs": []}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for freeze in (False, True):
                res = run(Path(tmp), freeze, args.iterations, f"r{r}_{'frozen' if freeze else 'traced'}")
                out["runs"].append(res)
                print(f"round {r} {'frozen' if freeze else 'traced'}: median {res['median_s'] * 1e3:.1f} ms, "
                      f"mean {res['mean_s'] * 1e3:.1f} ms per iteration, first {res['first_s']:.2f} s, "
                      f"final loss {res['final_loss']:.5f}", flush=True)
    out["reference_after"] = reference_loop_seconds()
    for freeze in (False, True):
        med = [r["median_s"] for r in out["runs"] if r["freeze"] == freeze]
        out["frozen" if freeze else "traced"] = {"median_of_medians_s": statistics.median(med)}
    ratio = out["frozen"]["median_of_medians_s"] / out["traced"]["median_of_medians_s"]
    out["ratio_frozen_to_traced"] = ratio
    print(f"frozen / traced, median seconds per iteration: {ratio:.3f}; reference loop "
          f"{out['reference_before']:.2f} / {out['reference_after']:.2f} s")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
