#!/usr/bin/env python
"""What ``psdr optimize --view`` costs the loop: one small optimisation run alternately without
and with the live viewer (psdr_cli/viewer/live.py), in this process, its iterations per second
measured between the first and the last iteration's progress report (so the observer's calls
between iterations are inside the interval). Because that rate varies with the machine's other
load, the viewer's own costs are measured too: the seconds spent in its calls on the loop's thread
(per iteration, and as a share of the run) and the CPU time of the threads the viewer started
(viser's server, the pusher) as a share of the run's wall time (/proc/self/task). With ``--browser``, the viewer's page is also open in
a headless chromium (software WebGL on the same cores: a pessimistic case on a small machine).

The scene is the test suite's (tests/test_optimize.py ``TINY``) at a ``--film`` × ``--film`` film,
without remeshing; each run is a fresh start (the previous one is moved aside).

    .venv/bin/python benchmarks/viewer_overhead.py [--iterations 150] [--repeats 3] [--browser] \\
        [--json docs/benchmarks/viewer_overhead.json]
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import shutil
import socket
import sys
import tempfile
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

from machine import reference_loop_seconds  # noqa: E402

from psdr_cli import api  # noqa: E402
from test_optimize import TINY  # noqa: E402


class Clock:
    """A progress object that notes when each iteration was reported."""

    def start(self, total, done=0):
        self.times = []

    def advance(self, n, loss=None):
        self.times.append(time.perf_counter())

    def rate(self) -> float:
        return (len(self.times) - 1) / (self.times[-1] - self.times[0])


def experiment(folder: Path, film: int, iterations: int):
    data = copy.deepcopy(TINY)
    data["scene"]["film"] = {"width": film, "height": film}
    data["optimize"].update(iterations=iterations, checkpoint_every=25, remesh={"method": "instant", "initial": 300})
    data["output"] = str(folder / "runs")
    path = folder / "viewer_overhead.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return api.load_experiment(path)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def headless_chromium(url: str):
    os.environ["SE_OFFLINE"] = "true"
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    opts = webdriver.ChromeOptions()
    opts.binary_location = shutil.which("chromium") or shutil.which("chromium-browser")
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1000,700",
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader"):
        opts.add_argument(arg)
    driver = webdriver.Chrome(options=opts, service=Service(shutil.which("chromedriver")))
    driver.get(url)
    return driver


def thread_cpu_seconds(native_ids) -> float:
    """CPU seconds (user + system) the threads ``native_ids`` of this process have used so far."""
    tick, total = os.sysconf("SC_CLK_TCK"), 0.0
    for tid in native_ids:
        try:
            fields = Path(f"/proc/self/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue  # ended
        total += (int(fields[11]) + int(fields[12])) / tick
    return total


def task_ids() -> set:
    return {int(t) for t in os.listdir("/proc/self/task")}


def one_run(exp, mode: str, costs: dict) -> float:
    """Iterations per second of one fresh run: ``off``, ``view`` or ``view+browser``; with a
    viewer, ``costs[mode]`` gets the seconds per iteration spent in the observer's calls on the
    loop's thread and the viewer's threads' CPU seconds per second of the run."""
    clock, viewer, driver = Clock(), None, None
    if mode != "off":
        before = task_ids()
        viewer = api.live_viewer(port=free_port(), warn=lambda m: print("warning:", m))
        threads = task_ids() - before
        if mode == "view+browser":
            driver = headless_chromium(viewer.url)
        inside = [0.0]
        call = viewer.iteration

        def timed(*args):
            t = time.perf_counter()
            call(*args)
            inside[0] += time.perf_counter() - t
        viewer.iteration = timed
        cpu0 = thread_cpu_seconds(threads | (task_ids() - before))
    t0 = time.perf_counter()
    try:
        api.optimize(exp, progress=clock, warn=lambda m: None, observer=viewer)
    finally:
        if viewer:
            wall = time.perf_counter() - t0
            cpu = thread_cpu_seconds(threads | (task_ids() - before)) - cpu0
            n = len(clock.times)
            costs.setdefault(mode, []).append({"observer_ms_per_iteration": 1e3 * inside[0] / n,
                                               "observer_share_of_loop": inside[0] / wall,
                                               "viewer_threads_cpu_share": cpu / wall})
        if driver:
            driver.quit()
        if viewer:
            viewer.close()
    return clock.rate()


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=150)
    ap.add_argument("--film", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--browser", action="store_true")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    modes = ["off", "view"] + (["view+browser"] if args.browser else [])
    with tempfile.TemporaryDirectory() as tmp:
        exp = experiment(Path(tmp), args.film, args.iterations)
        costs = {}
        one_run(exp, "off", costs)  # warm-up: targets rendered, kernels compiled
        rates = {m: [] for m in modes}
        reference = [reference_loop_seconds()]
        for r in range(args.repeats):
            for m in modes:  # alternated, so that a drift of the machine's load hits every mode alike
                rates[m].append(one_run(exp, m, costs))
                print(f"repeat {r}: {m}: {rates[m][-1]:.2f} iterations/s", flush=True)
        reference.append(reference_loop_seconds())
    median = {m: sorted(v)[len(v) // 2] for m, v in rates.items()}
    result = {"iterations": args.iterations, "film": args.film, "repeats": args.repeats, "push_interval_s": 1.0,
              "iterations_per_second": rates, "median": median,
              "cost_percent": {m: 100 * (1 - median[m] / median["off"]) for m in modes if m != "off"},
              "viewer_costs": costs,
              "reference_loop_seconds": reference, "cpus": os.cpu_count()}
    print(json.dumps(result, indent=1))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
