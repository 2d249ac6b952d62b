#!/usr/bin/env python
"""Equal-time benchmark of forward-mode gradient images: psdr's estimator vs Mitsuba's
``prb_projective``.

For every validation scene (``configs/validation/*.yaml``) the total gradient image dI/dθ of view 0
is estimated by

- **ours**: ``interior + primary + direct + indirect`` (``psdr_cli.rendering.estimate.forward_gradient``,
  MIS boundary sampling, the same spp for every term);
- **Mitsuba**: ``prb_projective`` with guiding off (``psdr_cli.rendering.reference.mitsuba_projective``);

both in the same process. Steps per scene:

1. High-sample references: ours (``--ref-spp`` × ``--ref-seeds``), Mitsuba (``--mi-ref-spp`` ×
   ``--mi-ref-seeds``) and central finite differences (``--fd-spp`` in 8 batches, step ``--fd-h``).
   Their image sums (± standard error over seeds/batches) show any bias.
2. Warm-up: each method once at every sample count it is timed at (kernel compilation).
3. Equal time: ours at ``--spp`` per term gives a wall time T; Mitsuba's spp is calibrated so its
   time is ≈ T (proportional scaling, then secant steps, each re-measured). Then ``--trials``
   interleaved trials with seeds 1..K; relMSE = mean((g − ref)²) / mean(ref²) against our
   high-sample reference; the per-pixel variance across the trials separates noise from bias.

Outputs (written atomically, refreshed after every scene): ``<out>/gradients.json`` and
``<out>/gradients.md``.

    .venv/bin/python benchmarks/gradients.py            # full run (≈ 6–7 min on 2 idle cores)
    .venv/bin/python benchmarks/gradients.py --quick    # smoke run (≈ 1 min)
    .venv/bin/python benchmarks/gradients.py --wait-idle 120   # wait out other jobs before timing

Real-mesh stand-ins (``tests/standins.py``, the scenes of ``tests/test_real_mesh_gradients.py``):

    .venv/bin/python benchmarks/gradients.py --standins              # every stand-in, ≈ 5 min
    .venv/bin/python benchmarks/gradients.py --standins eyes camera_rotate
    .venv/bin/python benchmarks/gradients.py --smooth-cost           # smooth vs flat blob timing

give the FD verdict (sum z, tiles) of ours and of ``prb_projective`` and the time of a gradient,
in ``<out>/gradients_real_meshes.{json,md}`` (a run with some scenes keeps the others' rows).

Timings are only meaningful on an otherwise idle machine: every equal-time row records the CPU
that other processes used meanwhile ("other processes (cores)").
"""
from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))  # standins: the real-mesh stand-in scenes the tests share

import psdr_cli  # noqa: E402  (configures Dr.Jit / LLVM before drjit is imported)
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import standins  # noqa: E402
from psdr_cli import api  # noqa: E402
from psdr_cli.commands.compare import rel_mse  # noqa: E402
from psdr_cli.config.vocabularies import TERMS  # noqa: E402
from psdr_cli.experiment.load import load_experiment  # noqa: E402
from psdr_cli.rendering.estimate import forward_gradient, prepare  # noqa: E402
from psdr_cli.rendering.reference import agreement, block_sums, fd_resolution, finite_difference, mitsuba_projective  # noqa: E402
from psdr_cli.rendering.render import render_view  # noqa: E402
from psdr_cli.support.fileio import atomic_path  # noqa: E402
from psdr_cli.support.verdict import agrees, checks  # noqa: E402

SCENES = ("silhouette", "shadow", "bunny", "cornell")
FD_BATCHES = 8
#: The silhouette's finite differences are all edge noise and each sample is cheap (max_depth 1).
FD_SPP_SCALE = {"silhouette": 8}


# --------------------------------------------------------------------------------------------
# Small helpers
# --------------------------------------------------------------------------------------------
def log(msg: str):
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def mean_se(values):
    """Mean and standard error of the mean of independent values."""
    v = np.asarray(values, np.float64)
    se = float(v.std(ddof=1) / np.sqrt(len(v))) if len(v) > 1 else float("nan")
    return float(v.mean()), se


def tile_correlation(a, b, block: int = 4) -> float:
    """Correlation of two images' block×block tile sums (channels summed)."""
    x, y = block_sums([a], block)[0].ravel(), block_sums([b], block)[0].ravel()
    if x.std() == 0 or y.std() == 0:
        return float("nan")
    return float(np.corrcoef(x, y)[0, 1])


class ForeignLoad:
    """CPU time used by *other* processes while a block runs, in cores (Linux /proc): all busy
    jiffies of the machine minus this process's own. Timings taken while it is well above 0 are
    perturbed (the machine has only a few cores)."""

    HZ = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100

    @staticmethod
    def _busy():
        try:
            f = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
            total = sum(f[:3]) + sum(f[5:8])          # user nice system (idle iowait) irq softirq steal
            own = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
            return total, int(own[11]) + int(own[12])  # utime + stime of every thread of this process
        except (OSError, ValueError, IndexError):
            return None

    def __enter__(self):
        self.t0, self.b0 = time.perf_counter(), self._busy()
        self.cores = float("nan")
        return self

    def __exit__(self, *exc):
        b1, dt = self._busy(), time.perf_counter() - self.t0
        if self.b0 and b1 and dt > 0:
            self.cores = max(0.0, ((b1[0] - self.b0[0]) - (b1[1] - self.b0[1])) / self.HZ / dt)
        return False


#: Other processes' CPU use (cores) above which an equal-time block counts as perturbed.
PERTURBED = 0.25


def wait_for_idle(max_seconds: float, threshold: float = 0.2):
    """Wait (at most ``max_seconds``) until other processes use less than ``threshold`` cores."""
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < max_seconds:
        with ForeignLoad() as load:
            time.sleep(2.0)
        if load.cores < threshold:
            return
        log(f"  waiting: other processes use {load.cores:.2f} cores")


def write_atomic(path: Path, text: str):
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def git_state() -> dict:
    def git(*args):
        try:
            return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True,
                                  timeout=10).stdout.strip()
        except Exception:  # noqa: BLE001 - git missing: not essential
            return ""
    return {"commit": git("rev-parse", "HEAD"), "dirty": bool(git("status", "--porcelain", "--untracked-files=no"))}


def machine_info(variant: str) -> dict:
    cpu = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu_count": os.cpu_count(), "cpu_model": cpu or platform.processor(), "platform": platform.platform(),
            "python": platform.python_version(), "numpy": np.__version__, "mitsuba": mi.__version__,
            "drjit": dr.__version__, "variant": variant, "psdr_cli": psdr_cli.__version__}


# --------------------------------------------------------------------------------------------
# The two estimators, timed the same way: wall time of the call that returns the numpy image
# --------------------------------------------------------------------------------------------
class Bench:
    """One validation scene with both estimators and the finite-difference reference."""

    def __init__(self, config: Path, smooth: bool = False):
        self.config = config
        self.config_text = Path(config).read_text()
        self.exp = load_experiment(config)
        if smooth:  # shading check: every object whose edges are sampled smooth-shaded
            for o in self.exp.scene.objects:
                o.smooth = o.smooth or o.edges
        self.scene, self.parameter, self.edges, settings = prepare(self.exp)
        self.variant = mi.variant()
        mi.set_log_level(mi.LogLevel.Error)
        # every term at the same spp, unguided MIS over unsorted edges, one pass
        self.settings = settings.with_estimator(sampling="mis", guiding="none", edge_sort=False, passes=1)
        self.max_depth = self.exp.scene.max_depth

    def ours(self, spp: int, seed: int):
        """Total gradient image of our estimator (every term at ``spp``) and its wall time."""
        settings = replace(self.settings.with_estimator(spp=spp, primary_spp=spp, boundary_spp=spp), seed=seed)
        t0 = time.perf_counter()
        estimates = [forward_gradient(self.scene, self.edges, self.parameter, 0, t, settings) for t in TERMS]
        g = sum(e.gradient for e in estimates)
        seconds = time.perf_counter() - t0
        return g, seconds, {e.term: float(e.gradient.sum()) for e in estimates}

    def mitsuba(self, spp: int, seed: int):
        """Gradient image of Mitsuba's prb_projective (guiding off) and its wall time."""
        t0 = time.perf_counter()
        g = mitsuba_projective(self.scene, self.parameter, 0, spp, seed=seed, batches=1)[0]
        return g, time.perf_counter() - t0

    def fd(self, h: float, spp: int, seed: int):
        t0 = time.perf_counter()
        batches = finite_difference(self.scene, self.parameter, 0, h, spp, seed=seed, batches=FD_BATCHES)
        return batches, time.perf_counter() - t0


# --------------------------------------------------------------------------------------------
# Benchmark steps
# --------------------------------------------------------------------------------------------
def references(b: Bench, args) -> dict:
    """High-sample images of ours, Mitsuba and finite differences, with their image sums."""
    out = {}
    imgs, sums, secs = [], [], 0.0
    for k in range(args.ref_seeds):
        g, s, _ = b.ours(args.ref_spp, 10_000 + k)
        imgs.append(g), sums.append(g.sum())
        secs += s
    ours = np.mean(imgs, axis=0)
    m, se = mean_se(sums)
    out["ours"] = {"spp_per_term": args.ref_spp, "seeds": args.ref_seeds, "sum": m, "sum_se": se,
                   "seconds": secs, "per_seed_sums": [float(x) for x in sums]}
    log(f"  reference ours    {args.ref_seeds} × {args.ref_spp} spp/term: sum {m:+.4g} ± {se:.2g} ({secs:.1f} s)")

    imgs, sums, secs = [], [], 0.0
    for k in range(args.mi_ref_seeds):
        g, s = b.mitsuba(args.mi_ref_spp, 10_000 + k)
        imgs.append(g), sums.append(g.sum())
        secs += s
    mits = np.mean(imgs, axis=0)
    m, se = mean_se(sums)
    out["mitsuba"] = {"spp": args.mi_ref_spp, "seeds": args.mi_ref_seeds, "sum": m, "sum_se": se,
                      "seconds": secs, "per_seed_sums": [float(x) for x in sums],
                      "max_abs_pixel_per_seed": [float(np.abs(x).max()) for x in imgs]}
    log(f"  reference Mitsuba {args.mi_ref_seeds} × {args.mi_ref_spp} spp: sum {m:+.4g} ± {se:.2g} ({secs:.1f} s)")

    fd_spp = args.fd_spp * FD_SPP_SCALE.get(b.exp.name, 1)
    batches, secs = b.fd(args.fd_h, fd_spp, seed=1)
    fd = np.mean(batches, axis=0)
    m, se = mean_se([x.sum() for x in batches])
    out["fd"] = {"h": args.fd_h, "spp": fd_spp, "batches": FD_BATCHES, "sum": m, "sum_se": se, "seconds": secs}
    log(f"  finite diff. h={args.fd_h:g}, {fd_spp} spp in {FD_BATCHES} batches: sum {m:+.4g} ± {se:.2g} "
        f"({secs:.1f} s)")

    for name in ("ours", "mitsuba"):
        r = out[name]
        r["z_vs_fd"] = float((r["sum"] - out["fd"]["sum"]) / np.hypot(r["sum_se"], out["fd"]["sum_se"]))
        r["tile_correlation_vs_fd"] = tile_correlation(ours if name == "ours" else mits, fd)
    out["mitsuba"]["rel_mse_vs_ours_reference"] = rel_mse(mits, ours)
    return out, ours, mits


def time_mitsuba(b: Bench, spp: int, runs: int = 2) -> float:
    """Median wall time of Mitsuba at ``spp`` after one untimed (compiling) call."""
    b.mitsuba(spp, 900)
    return float(np.median([b.mitsuba(spp, 901 + i)[1] for i in range(runs)]))


def calibrate(b: Bench, target: float, start: int, tol: float, max_steps: int = 5) -> tuple[int, list]:
    """Mitsuba spp whose wall time is ≈ ``target``: proportional scaling from ``start``, then
    secant steps through the last two measurements."""
    points = []
    spp = start
    for _ in range(max_steps):
        t = time_mitsuba(b, spp)
        points.append((spp, t))
        log(f"    calibrate Mitsuba: {spp} spp → {t * 1000:.1f} ms (target {target * 1000:.1f} ms)")
        if abs(t - target) <= tol * target:
            break
        if len(points) >= 2 and points[-1][0] != points[-2][0]:
            (s0, t0), (s1, t1) = points[-2], points[-1]
            slope = (t1 - t0) / (s1 - s0)
            new = s1 + (target - t1) / slope if slope > 0 else s1 * target / t1
        else:
            new = spp * target / t
        new = max(1, int(round(new)))
        if any(new == s for s, _ in points):
            break
        spp = new
    best = min(points, key=lambda p: abs(p[1] - target))
    return best[0], [{"spp": s, "seconds": t} for s, t in points]


def equal_time(b: Bench, spp: int, args, ours_ref) -> dict:
    """Equal-time comparison at ``spp`` per term for ours."""
    b.ours(spp, 900)                                            # warm-up (compilation)
    for attempt in range(1, (args.retries if args.wait_idle else 0) + 2):
        if args.wait_idle:
            wait_for_idle(args.wait_idle)
        with ForeignLoad() as load:
            res = _equal_time(b, spp, args, ours_ref)
        res["other_processes_cores"], res["attempt"] = load.cores, attempt
        if not load.cores > PERTURBED:
            break
        log(f"  note: other processes used {load.cores:.2f} cores meanwhile; these timings are perturbed")
    return res


def _equal_time(b: Bench, spp: int, args, ours_ref) -> dict:
    target = float(np.median([b.ours(spp, 901 + i)[1] for i in range(3)]))
    log(f"  ours {spp} spp/term: {target * 1000:.1f} ms (median of 3 after warm-up)")
    mi_spp, calibration = calibrate(b, target, spp, args.tol)
    log(f"  Mitsuba spp for equal time: {mi_spp}")
    rows, images = {"ours": [], "mitsuba": []}, {"ours": [], "mitsuba": []}
    for k in range(1, args.trials + 1):                         # interleaved: both see the same load
        c0 = time.process_time()
        g, s, _ = b.ours(spp, k)
        c = time.process_time() - c0
        images["ours"].append(g)
        rows["ours"].append({"seed": k, "seconds": s, "cpu_seconds": c, "sum": float(g.sum()),
                             "rel_mse": rel_mse(g, ours_ref), "max_abs_pixel": float(np.abs(g).max())})
        c0 = time.process_time()
        g, s = b.mitsuba(mi_spp, k)
        c = time.process_time() - c0
        images["mitsuba"].append(g)
        rows["mitsuba"].append({"seed": k, "seconds": s, "cpu_seconds": c, "sum": float(g.sum()),
                                "rel_mse": rel_mse(g, ours_ref), "max_abs_pixel": float(np.abs(g).max())})
    best_time = min(c["seconds"] for c in calibration)
    res = {"calibration": calibration,
           # False when even the cheapest Mitsuba run measured was slower than ours (fixed per-call cost)
           "equal_time_reached": bool(best_time <= target * (1 + args.tol) or mi_spp > 1)}
    for name, n in (("ours", spp), ("mitsuba", mi_spp)):
        r = rows[name]
        e = [x["rel_mse"] for x in r]
        # Noise alone, without a reference: per-pixel variance across the trials (unbiased), relative
        # to the same mean(ref²) as relMSE. relMSE ≈ rel_variance + relative squared bias.
        rel_var = float(np.var(images[name], axis=0, ddof=1).mean() / np.mean(ours_ref ** 2))
        res[name] = {"spp": n, "seconds_mean": float(np.mean([x["seconds"] for x in r])),
                     "seconds_median": float(np.median([x["seconds"] for x in r])),
                     "cpu_seconds_mean": float(np.mean([x["cpu_seconds"] for x in r])),
                     "rel_mse_mean": float(np.mean(e)), "rel_mse_median": float(np.median(e)),
                     "rel_mse_se": mean_se(e)[1], "rel_variance": rel_var,
                     "trials": r}
    o, m = res["ours"], res["mitsuba"]
    res["ratio_mean"] = m["rel_mse_mean"] / o["rel_mse_mean"]
    res["ratio_median"] = m["rel_mse_median"] / o["rel_mse_median"]
    res["ratio_variance"] = m["rel_variance"] / o["rel_variance"]
    # Work-normalised (error × time) ratio, which also corrects a residual time mismatch; meaningful
    # where the error is noise (∝ 1/time), not where it is bias.
    res["ratio_time_adjusted"] = res["ratio_mean"] * m["seconds_mean"] / o["seconds_mean"]
    log(f"  equal time: ours {o['spp']} spp {o['seconds_mean'] * 1000:.0f} ms relMSE {o['rel_mse_mean']:.3g} "
        f"(median {o['rel_mse_median']:.3g}) | Mitsuba {m['spp']} spp {m['seconds_mean'] * 1000:.0f} ms relMSE "
        f"{m['rel_mse_mean']:.3g} (median {m['rel_mse_median']:.3g}) | ratio {res['ratio_mean']:.3g}"
        f"{'' if res['equal_time_reached'] else ' (Mitsuba slower even at 1 spp)'}")
    return res


# --------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------
def fmt(x, digits=3):
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "–"
    return f"{x:.{digits}g}"


def bias_phrase(r: dict) -> str:
    """Which high-sample image sums agree with finite differences (|z| ≤ 3)."""
    def verdict(z):
        return "disagrees" if abs(z) > 3 else "agrees, borderline" if abs(z) > 2.5 else "agrees"
    parts = [f"{'ours' if k == 'ours' else 'Mitsuba'} {verdict(r[k]['z_vs_fd']).split(',')[0]} "
             f"(z = {r[k]['z_vs_fd']:+.1f}{', borderline' if 'borderline' in verdict(r[k]['z_vs_fd']) else ''})"
             for k in ("ours", "mitsuba")]
    return " and ".join(parts)


def overall(report: dict) -> str:
    """One generated paragraph over all scenes."""
    rows = [(n, et) for n, sc in report["scenes"].items() for et in sc["equal_time"]]
    fair = [(n, et) for n, et in rows if et["equal_time_reached"]]
    wins = sum(et["ratio_mean"] > 1 for _, et in fair)
    med = [et["ratio_median"] for _, et in fair]
    var_lose = [f"{n} {et['ours']['spp']}" for n, et in fair if et["ratio_variance"] < 1]
    mi_biased = [n for n, sc in report["scenes"].items() if abs(sc["references"]["mitsuba"]["z_vs_fd"]) > 3]
    ours_biased = [n for n, sc in report["scenes"].items() if abs(sc["references"]["ours"]["z_vs_fd"]) > 3]
    ours_chk = [n for n, sc in report["scenes"].items()
                if sc.get("smooth_shading_check") and abs(sc["smooth_shading_check"]["ours"]["z_vs_fd"]) > 3]
    text = (f"In the {len(fair)} rows where equal time was reached, ours has the lower mean relMSE in {wins}; "
            f"the ratio of median relMSEs (Mitsuba / ours) ranges from {fmt(min(med))} to {fmt(max(med))}. "
            if fair else "")
    if var_lose:
        text += f"Counting noise alone, Mitsuba is less noisy in: {', '.join(var_lose)} spp/term. "
    text += (f"Mitsuba's high-sample image sum disagrees with finite differences in: {', '.join(mi_biased)}; "
             if mi_biased else "Mitsuba's high-sample image sums agree with finite differences; ")
    text += (f"ours disagrees in: {', '.join(ours_biased)}." if ours_biased
             else "ours agrees in every validation scene.")
    if ours_chk:
        text += (f" In the shading check (not a validation config) ours disagrees with finite differences "
                 f"for: {', '.join(ours_chk)}.")
    return text


def summary_lines(report: dict) -> list:
    """One bullet per scene, read off the numbers (nothing here is written by hand): who has the
    lower error at equal time, whether Mitsuba's error is mostly bias or noise, whether its fixed
    per-call cost decides the low-spp rows, and which high-sample sums disagree with FD."""
    out = []
    for name, sc in report["scenes"].items():
        r, eqs = sc["references"], sc["equal_time"]
        ratios = ", ".join(f"{fmt(et['ratio_mean'])} at {et['ours']['spp']}" for et in eqs)
        text = [f"relMSE ratio Mitsuba/ours {ratios} spp/term ({'ours lower' if all(e['ratio_mean'] > 1 for e in eqs) else 'mixed' if any(e['ratio_mean'] > 1 for e in eqs) else 'Mitsuba lower'})."]
        short = [et for et in eqs if not et["equal_time_reached"]]
        if short:
            text.append(f"At {', '.join(str(et['ours']['spp']) for et in short)} spp/term Mitsuba's fixed "
                        "per-call cost exceeds our whole time (even 1 spp is slower), so that row favours us"
                        + (f"; the {eqs[-1]['ours']['spp']}-spp row (ratio {fmt(eqs[-1]['ratio_mean'])}) is the "
                           "fairer per-sample comparison." if eqs[-1]["equal_time_reached"] else "."))
        text.append("Noise alone (ratio of relative variances): "
                    + ", ".join(f"{fmt(et['ratio_variance'])} at {et['ours']['spp']}" for et in eqs) + " spp/term"
                    + ("; ours is the noisier estimator at "
                       + ", ".join(str(et["ours"]["spp"]) for et in eqs if et["ratio_variance"] < 1) + " spp/term."
                       if any(et["ratio_variance"] < 1 for et in eqs) else "."))
        biased = [et for et in eqs if et["mitsuba"]["rel_mse_median"] > 2 * et["mitsuba"]["rel_variance"]]
        if biased:
            text.append("Mitsuba's error is mostly bias at "
                        + ", ".join(f"{et['ours']['spp']}" for et in biased) + " spp/term (median relMSE "
                        + ", ".join(fmt(et["mitsuba"]["rel_mse_median"]) for et in biased) + " vs relative variance "
                        + ", ".join(fmt(et["mitsuba"]["rel_variance"]) for et in biased) + ").")
        spiky = [et for et in eqs if et["mitsuba"]["rel_mse_mean"] > 3 * et["mitsuba"]["rel_mse_median"]]
        for et in spiky:
            text.append(f"At {et['ours']['spp']} spp/term a Mitsuba firefly dominates its mean relMSE "
                        f"({fmt(et['mitsuba']['rel_mse_mean'])} vs median {fmt(et['mitsuba']['rel_mse_median'])}).")
        text.append(f"High-sample image sums vs finite differences: {bias_phrase(r)}.")
        chk = sc.get("smooth_shading_check")
        if chk:
            flat = ", ".join(o for o, sh in sc["shading"].items() if sh == "flat")
            text.append(f"With {flat} smooth-shaded instead (shading check): {bias_phrase(chk)}.")
        out.append(f"- **{name}**: " + " ".join(text))
    return out


def markdown(report: dict) -> str:
    mach, args = report["machine"], report["settings"]
    L = ["# Gradient benchmark: ours vs Mitsuba `prb_projective` at equal time", "",
         f"Generated by `benchmarks/gradients.py` on {report['date']} "
         f"({'quick run' if args['quick'] else 'full run'}, {report['total_seconds'] / 60:.1f} min). "
         f"Machine: {mach['cpu_count']} CPU cores ({mach['cpu_model']}), variant `{mach['variant']}`, "
         f"Mitsuba {mach['mitsuba']}, Dr.Jit {mach['drjit']}. Commit `{report['git']['commit'][:10]}`"
         f"{' (working tree with uncommitted changes)' if report['git']['dirty'] else ''}. "
         "All numbers, per trial, are in `gradients.json`.", "",
         "The quantity is the **total** forward-mode gradient image dI/dθ of view 0 of each validation "
         "scene (`configs/validation/`), θ as in the scene's `parameter:`. Both estimators run in the "
         "same process, one after the other.", "",
         "## Method", "",
         "- **Ours**: `interior + primary + direct + indirect` from `forward_gradient`, MIS boundary "
         "sampling, the same spp for every term.",
         "- **Mitsuba**: `prb_projective` (forward mode through `mi.render`, guiding `none`, same "
         "`max_depth`), via `psdr_cli.rendering.reference.mitsuba_projective`.",
         f"- **Reference**: our estimator at {args['ref_spp']} spp per term in {args['ref_seeds']} seeds, "
         f"averaged ({args['ref_spp'] * args['ref_seeds']} spp per term). relMSE = mean((g − ref)²) / "
         "mean(ref²) over pixels and channels, averaged over the trials.",
         "- **Relative variance**: the per-pixel variance across the trials (unbiased), averaged and "
         "divided by the same mean(ref²). It needs no reference, so it measures each method's noise "
         "alone; relMSE ≈ relative variance + relative squared bias.",
         f"- **Equal time**: every method is run once untimed at each sample count before it is timed "
         f"(kernel compilation). Our wall time T is the median of 3 runs; Mitsuba's spp starts at ours, "
         f"is scaled proportionally to T and then corrected by secant steps, each re-measured, until "
         f"within {args['tol'] * 100:.0f} %. Then {args['trials']} trials per method with seeds "
         f"1..{args['trials']}, ours and Mitsuba interleaved so both see the same machine load. The "
         "seconds below are the means measured in those trials (wall time of the call that returns "
         "the numpy image). *Time-adjusted ratio* = ratio × (Mitsuba s / ours s), the error × time "
         "ratio, which removes a residual time mismatch when the error is noise.",
         f"- **Bias check**: Mitsuba at {args['mi_ref_spp']} spp in {args['mi_ref_seeds']} seeds, and "
         f"central finite differences (common random numbers, h = {args['fd_h']:g}, "
         f"{args['fd_spp']} spp in {FD_BATCHES} batches"
         + (f"; ×{FD_SPP_SCALE['silhouette']} for the cheap silhouette scene" if 'silhouette' in report['scenes'] else "")
         + ") of the image sum, ± standard error over seeds or batches; "
         "z = (sum − FD) / √(se² + se_FD²).", "",
         "## Equal-time error", "",
         "| scene | ours spp/term | ours s | ours relMSE | Mitsuba spp | Mitsuba s | Mitsuba relMSE "
         "| **ratio** (Mitsuba / ours) | time-adjusted ratio | other processes (cores) |",
         "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    footnote = False
    for name, sc in report["scenes"].items():
        for et in sc["equal_time"]:
            o, m = et["ours"], et["mitsuba"]
            mark = "" if et["equal_time_reached"] else " †"
            footnote |= not et["equal_time_reached"]
            L.append(f"| {name} | {o['spp']} | {o['seconds_mean']:.3f} | {fmt(o['rel_mse_mean'])} | {m['spp']}{mark} | "
                     f"{m['seconds_mean']:.3f} | {fmt(m['rel_mse_mean'])} | **{fmt(et['ratio_mean'])}** | "
                     f"{fmt(et['ratio_time_adjusted'])} | {et['other_processes_cores']:.2f}"
                     f"{' ‡' if et['other_processes_cores'] > PERTURBED else ''} |")
    if footnote:
        L += ["", "† Mitsuba at 1 spp already takes longer than ours (its fixed per-call cost), so equal "
              "time could not be reached; the row compares Mitsuba's cheapest run with ours."]
    L += ["", "*Other processes*: CPU used by the rest of the machine during the block (calibration and "
          "trials), from /proc/stat; well above 0 means the timings of that row were perturbed "
          f"(‡: more than {PERTURBED} cores, read that row with care)."]
    L += ["", "Noise and robustness: medians over the trials (less sensitive to rare fireflies) and the "
          "reference-free relative variance.", "",
          "| scene | ours spp | ours relMSE median | ours rel. variance | Mitsuba spp | Mitsuba relMSE median "
          "| Mitsuba rel. variance | ratio of medians | ratio of variances |",
          "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, sc in report["scenes"].items():
        for et in sc["equal_time"]:
            o, m = et["ours"], et["mitsuba"]
            L.append(f"| {name} | {o['spp']} | {fmt(o['rel_mse_median'])} | {fmt(o['rel_variance'])} | {m['spp']} | "
                     f"{fmt(m['rel_mse_median'])} | {fmt(m['rel_variance'])} | {fmt(et['ratio_median'])} | "
                     f"{fmt(et['ratio_variance'])} |")
    L += ["", "## High-sample results vs finite differences (image sums)", "",
          "| scene | parameter | ours sum | z vs FD | Mitsuba sum | z vs FD | FD sum | Mitsuba relMSE vs our ref "
          "| tile corr. ours/FD | tile corr. Mitsuba/FD |",
          "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, sc in report["scenes"].items():
        r = sc["references"]
        o, m, f = r["ours"], r["mitsuba"], r["fd"]
        L.append(f"| {name} | {sc['parameter']} | {o['sum']:+.4g} ± {o['sum_se']:.2g} | {o['z_vs_fd']:+.2f} | "
                 f"{m['sum']:+.4g} ± {m['sum_se']:.2g} | {m['z_vs_fd']:+.2f} | {f['sum']:+.4g} ± {f['sum_se']:.2g} | "
                 f"{fmt(m['rel_mse_vs_ours_reference'])} | {fmt(o['tile_correlation_vs_fd'])} | "
                 f"{fmt(m['tile_correlation_vs_fd'])} |")
    checks = {n: sc for n, sc in report["scenes"].items() if sc.get("smooth_shading_check")}
    if checks:
        L += ["", "**Shading check** (not the validation configs): the same high-sample results with every "
              "flat-shaded object whose edges are sampled switched to smooth shading, which removes the "
              "facet (crease) discontinuities from the image.", "",
              "| scene | smooth-shaded | ours sum | z vs FD | Mitsuba sum | z vs FD | FD sum |",
              "|---|---|---:|---:|---:|---:|---:|"]
        for name, sc in checks.items():
            c = sc["smooth_shading_check"]
            o, m, f = c["ours"], c["mitsuba"], c["fd"]
            flat = ", ".join(k for k, sh in sc["shading"].items() if sh == "flat")
            L.append(f"| {name} | {flat} | {o['sum']:+.4g} ± {o['sum_se']:.2g} | {o['z_vs_fd']:+.2f} | "
                     f"{m['sum']:+.4g} ± {m['sum_se']:.2g} | {m['z_vs_fd']:+.2f} | {f['sum']:+.4g} ± {f['sum_se']:.2g} |")
    L += ["", "'Mitsuba relMSE vs our ref' compares the two high-sample images (it includes the remaining "
          "noise of both). Tile correlation: correlation of 4×4-pixel tile sums of the high-sample image "
          "with the finite-difference image (FD tiles are noisy, so even an exact gradient stays below 1).", "",
          "## What the numbers say (generated from the numbers above)", "", overall(report), ""]
    L += summary_lines(report) + [""]
    L += ["## Caveats", "",
          f"- {mach['cpu_count']} CPU cores, LLVM backend, tiny images (32×32, the bunny 48×48): fixed "
          "per-call costs (Python tracing, kernel launches, AD graph traversal) are a large share of "
          "every timing, so the equal-time sample counts are not what large images on a GPU would give.",
          "- The reference is our own estimator. Where Mitsuba is biased (see the finite-difference table) "
          "its relMSE against our reference contains that bias, which does not shrink with more samples; "
          "the relative variance isolates its noise.",
          "- Shading of the objects whose edges are sampled: "
          + "; ".join(f"{n}: " + ", ".join(f"{o} {sh}" for o, sh in sc["shading"].items())
                      for n, sc in report["scenes"].items())
          + ". Mitsuba's projective integrator is known to miss the facet (crease) edges of flat-shaded "
          "meshes, so a bias of Mitsuba is expected in the scenes with flat-shaded objects.",
          "- Mitsuba's estimate occasionally has fireflies (rare, very large pixels), so its mean relMSE "
          f"over {args['trials']} trials is itself noisy; compare the medians too.",
          "- Wall times on a shared 2-core machine vary by some percent between runs.", ""]
    return "\n".join(L)

# --------------------------------------------------------------------------------------------
# Real-mesh stand-ins: FD verdict of ours and prb_projective, time of a gradient
# --------------------------------------------------------------------------------------------
def smooth_counts(cfg: dict) -> dict:
    """``cfg`` at the smooth stand-ins' sample counts (interior 512, primary and boundary 2048)."""
    cfg["estimator"] = {"spp": 512, "primary_spp": 2048, "boundary_spp": 2048}
    return cfg


#: name: (experiment dictionary, procedural meshes, FD step, FD spp in 8 batches)
STANDINS = {
    # off the icosphere's symmetry plane: from x = 0 one crease lies exactly on a pixel boundary
    "flat_blob": (lambda: standins.off_axis(standins.blob_cfg(False)), lambda: {"blob": standins.bumpy_blob()},
                  0.005, 16384),
    # the counts and FD step of its test (at h = 0.005 one tile beside the terminator is FD step error)
    "smooth_blob": (lambda: standins.blob_cfg(True, spp=(512, 2048, 2048)), lambda: {"blob": standins.bumpy_blob()},
                    0.0015, 65536),
    "smooth_dome": (lambda: standins.blob_cfg(True, spp=(512, 2048, 2048)), lambda: {"blob": standins.open_dome()},
                    0.0015, 32768),
    "smooth_resting_blob": (lambda: standins.blob_cfg(True, spp=(512, 2048, 2048)),
                            lambda: {"blob": standins.resting_blob()}, 0.0015, 32768),
    # at h = 0.005 a silhouette tile is FD step error
    "eyes": (standins.eye_cfg, lambda: {"head": standins.head_with_eye()}, 0.0015, 65536),
    "smooth_eyes": (lambda: smooth_counts(standins.eye_cfg(smooth=True)), lambda: {"head": standins.head_with_eye(1)},
                    0.0015, 32768),
    "smooth_eyes_rotate": (lambda: smooth_counts(standins.eye_cfg(smooth=True, kind="rotate")),
                           lambda: {"head": standins.head_with_eye(1)}, 0.003, 32768),
    "camera_translate": (lambda: standins.camera_cfg("translate"), dict, 0.003, 16384),
    "camera_rotate": (lambda: standins.camera_cfg("rotate"), dict, 0.003, 16384),
    # faces turned over, edges of more than two faces
    "turned_cube": (standins.part_cfg, lambda: {"part": standins.turned_cube()}, 0.003, 16384),
    "book": (standins.part_cfg, lambda: {"part": standins.book()}, 0.003, 16384),
    "joined_boxes": (standins.part_cfg, lambda: {"part": standins.joined_boxes()}, 0.003, 16384),
}
#: Mitsuba's samples per pixel per batch (8 batches) on the stand-ins.
STANDIN_MI_SPP = 256


def standin_experiment(name: str, folder: Path):
    cfg, mesh_arrays, _, _ = STANDINS[name]
    return standins.load(cfg(), folder, mesh_arrays())


def verdict_row(stats: dict) -> dict:
    """Sum z and the tile criteria of the shared verdict, flattened for the report."""
    row = {"sum": stats["sum"], "agrees": agrees(stats)}
    row.update({name: value for name, value, _, _ in checks(stats)})
    return row


def standin_row(name: str, folder: Path) -> dict:
    """FD verdict of ours (every term, 8 passes) and of prb_projective (8 batches), with times."""
    exp = standin_experiment(name, folder)
    _, _, h, fd_spp = STANDINS[name]
    with ForeignLoad() as load:
        t0 = time.perf_counter()
        est = api.gradient_images(exp, min_passes=8)
        ours_s = time.perf_counter() - t0
    scene, parameter, _, _ = prepare(exp)
    fd = finite_difference(scene, parameter, 0, h, fd_spp, seed=exp.seed, batches=FD_BATCHES)
    resolution = fd_resolution(render_view(scene, 0, 64, seed=exp.seed), h, fd_spp, FD_BATCHES)
    row = {"parameter": parameter.name, "fd": {"h": h, "spp": fd_spp},
           "ours": verdict_row(agreement([(e.passes, e.weights) for e in est.values()], fd, resolution=resolution)),
           "ours_seconds": ours_s, "ours_other_processes_cores": load.cores,
           "ours_spp": {"interior": exp.estimator.spp, "primary": exp.estimator.primary_spp,
                        "boundary": exp.estimator.boundary_spp, "passes": len(next(iter(est.values())).passes)}}
    log(f"{name}: ours sum z {row['ours']['sum']['z']:+.2f}, agrees {row['ours']['agrees']} ({ours_s:.1f} s)")
    try:
        t0 = time.perf_counter()
        batches = mitsuba_projective(scene, parameter, 0, STANDIN_MI_SPP, seed=5, batches=FD_BATCHES)
        row["mitsuba"] = verdict_row(agreement([(batches, None)], fd, resolution=resolution))
        row["mitsuba_seconds"] = time.perf_counter() - t0
        log(f"{name}: prb_projective sum z {row['mitsuba']['sum']['z']:+.2f}, agrees {row['mitsuba']['agrees']}")
    except RuntimeError as exc:
        cause = exc.__cause__ or exc  # dr.while_loop() wraps the integrator's own exception
        row["mitsuba_error"] = f"{type(cause).__name__}: {str(cause).splitlines()[0]}"
        log(f"{name}: prb_projective failed: {row['mitsuba_error']}")
    return row


def gradient_seconds(exp, runs: int = 3) -> dict:
    """Median wall time per term of one forward-mode gradient at the experiment's sample counts
    (one pass, after an untimed warm-up call)."""
    scene, parameter, edges, settings = prepare(exp)
    settings = settings.with_estimator(passes=1)
    out = {}
    for term in TERMS:
        forward_gradient(scene, edges, parameter, 0, term, settings)
        times = []
        for _ in range(runs):
            t0 = time.perf_counter()
            forward_gradient(scene, edges, parameter, 0, term, settings)
            times.append(time.perf_counter() - t0)
        out[term] = float(np.median(times))
    out["total"] = sum(out[t] for t in TERMS)
    return out


def smooth_cost(folder: Path) -> dict:
    """Time of a gradient of the bumpy blob smooth-shaded vs the same mesh flat-shaded (the flat
    blob's sample counts for both)."""
    out = {}
    with ForeignLoad() as load:
        for shading in ("flat", "smooth"):
            exp = standins.load(standins.blob_cfg(shading == "smooth"), folder, {"blob": standins.bumpy_blob()})
            out[shading] = gradient_seconds(exp)
            log(f"smooth cost: {shading} blob {out[shading]['total']:.2f} s per gradient")
    out["ratio"] = out["smooth"]["total"] / out["flat"]["total"]
    out["other_processes_cores"] = load.cores
    return out


def z_cell(row: dict, key: str) -> str:
    if key not in row:
        return f"raises `{row.get(key + '_error', 'not run')[:110]}`"
    r = row[key]
    s = r["sum"]
    return f"{s['estimate']:+.4g} ± {s['estimate_se']:.2g} (z {s['z']:+.2f})"


def tiles_cell(row: dict, key: str) -> str:
    if key not in row:
        return "–"
    r = row[key]
    return (f"{100 * r['tiles within 3 SE']:.0f} %, max {r['max |z| (signal tiles)']:.1f}, "
            f"z² {r['mean z²']:.2f}, corr {r['correlation']:.2f}: **{'agrees' if r['agrees'] else 'disagrees'}**")


def standin_markdown(report: dict) -> str:
    mach = report["machine"]
    L = ["# Real-mesh stand-ins: ours and `prb_projective` vs finite differences", "",
         f"Generated by `benchmarks/gradients.py --standins` (last run {report['date']}). Machine: "
         f"{mach['cpu_count']} CPU cores ({mach['cpu_model']}), variant `{mach['variant']}`, Mitsuba {mach['mitsuba']}, "
         f"Dr.Jit {mach['drjit']}. Commit `{report['git']['commit'][:10]}`"
         f"{' (uncommitted changes)' if report['git']['dirty'] else ''}. All numbers are in "
         "`gradients_real_meshes.json`.", "",
         "Scenes: `tests/standins.py` (those of `tests/test_real_mesh_gradients.py`), 32×32 px, 4×4 tiles. "
         "Ours: every term at the experiment's sample counts, 8 passes. Mitsuba: `prb_projective` (guiding off) at "
         f"{STANDIN_MI_SPP} spp in 8 batches, same scene, same `max_depth`. FD: central differences with "
         "common random numbers in 8 batches. Verdict: `psdr_cli.support.verdict` (sum |z| < 3, ≥ 90 % tiles within "
         "3 SE, mean z² < 2.5, max |z| on signal tiles < 5, correlation > 0.85).", "",
         "| scene | parameter | FD sum (h, spp) | ours spp (interior/primary/boundary × passes) | ours sum (z) "
         "| ours tiles | ours s (all passes) | prb_projective sum (z) | prb_projective tiles | other processes (cores) |",
         "|---|---|---:|---:|---:|---|---:|---:|---|---:|"]
    for name in [n for n in STANDINS if n in report["scenes"]]:
        row = report["scenes"][name]
        s, n = row["ours"]["sum"], row["ours_spp"]
        L.append(f"| {name} | {row['parameter']} | {s['fd']:+.4g} ± {s['fd_se']:.2g} ({row['fd']['h']:g}, "
                 f"{row['fd']['spp']}) | {n['interior']}/{n['primary']}/{n['boundary']} × {n['passes']} | "
                 f"{z_cell(row, 'ours')} | {tiles_cell(row, 'ours')} | "
                 f"{row['ours_seconds']:.1f} | {z_cell(row, 'mitsuba')} | {tiles_cell(row, 'mitsuba')} | "
                 f"{row['ours_other_processes_cores']:.2f} |")
    cost = report.get("smooth_cost")
    if cost:
        L += ["", "## Cost of smooth shading", "",
              "Median wall time of one forward-mode gradient (one pass, each term at the blob's sample "
              "counts, after a warm-up call) of the bumpy blob, flat-shaded vs the same mesh smooth-shaded:", "",
              "| shading | " + " | ".join(TERMS) + " | total |", "|---|" + "---:|" * (len(TERMS) + 1)]
        for shading in ("flat", "smooth"):
            L.append(f"| {shading} | " + " | ".join(f"{cost[shading][t]:.2f}" for t in TERMS)
                     + f" | {cost[shading]['total']:.2f} |")
        L += ["", f"Smooth / flat: **{cost['ratio']:.2f}×** (other processes used "
              f"{cost['other_processes_cores']:.2f} cores meanwhile; run `--smooth-cost` again after a change "
              "to the smooth-shading terms)."]
    L += ["", "The machine was shared with other jobs while these ran (column 'other processes'); the seconds "
          "are indicative only, the z values are not affected.", ""]
    return "\n".join(L)


def run_standins(args):
    """``--standins`` / ``--smooth-cost``: update ``<out>/gradients_real_meshes.{json,md}``."""
    path = args.out / "gradients_real_meshes.json"
    report = json.loads(path.read_text()) if path.exists() else {"scenes": {}}
    report.update(date=datetime.datetime.now().isoformat(timespec="seconds"), git=git_state())
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.standins or ():
            report["scenes"][name] = standin_row(name, Path(tmp))
            report["machine"] = machine_info(mi.variant())
            write_atomic(path, json.dumps(report, indent=1))
            write_atomic(args.out / "gradients_real_meshes.md", standin_markdown(report))
        if args.smooth_cost:
            report["smooth_cost"] = smooth_cost(Path(tmp))
            report["machine"] = machine_info(mi.variant())
    write_atomic(path, json.dumps(report, indent=1))
    write_atomic(args.out / "gradients_real_meshes.md", standin_markdown(report))
    log(f"wrote {path} and {args.out / 'gradients_real_meshes.md'}")


# --------------------------------------------------------------------------------------------
def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small run (fewer samples and trials)")
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), help="validation scenes to run")
    ap.add_argument("--spp", type=int, nargs="+", help="our samples per pixel per term for the equal-time "
                    "runs (default 16 64 256; quick: 16)")
    ap.add_argument("--trials", type=int, help="equal-time trials per method (default 8; quick: 3)")
    ap.add_argument("--ref-spp", type=int, help="our reference spp per term per seed (default 1024; quick: 256)")
    ap.add_argument("--ref-seeds", type=int, help="seeds of our reference (default 8; quick: 4)")
    ap.add_argument("--mi-ref-spp", type=int, help="Mitsuba reference spp per seed (default 1024; quick: 256)")
    ap.add_argument("--mi-ref-seeds", type=int, help="seeds of Mitsuba's reference (default 8; quick: 4)")
    ap.add_argument("--fd-spp", type=int, help="finite-difference spp, in 8 batches (default 16384; quick: 2048)")
    ap.add_argument("--fd-h", type=float, default=0.01, help="finite-difference step (θ units)")
    ap.add_argument("--tol", type=float, default=0.1, help="relative tolerance of the equal-time calibration")
    ap.add_argument("--no-shading-check", dest="shading_check", action="store_false",
                    help="skip re-running the high-sample bias check with flat-shaded objects smooth-shaded")
    ap.add_argument("--wait-idle", type=float, default=0.0, metavar="SECONDS",
                    help="before each equal-time block, wait up to this long for other processes to go idle")
    ap.add_argument("--retries", type=int, default=2,
                    help="with --wait-idle: repeat an equal-time block this often while other processes "
                         f"used more than {PERTURBED} cores during it")
    ap.add_argument("--standins", nargs="*", choices=list(STANDINS), metavar="NAME",
                    help=f"real-mesh stand-ins instead of the validation scenes (none named: all of "
                         f"{', '.join(STANDINS)})")
    ap.add_argument("--smooth-cost", action="store_true",
                    help="time a gradient of the smooth-shaded blob vs the same mesh flat-shaded")
    ap.add_argument("--render-only", action="store_true",
                    help="only rewrite <out>/gradients.md from an existing <out>/gradients.json")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks", help="output folder")
    args = ap.parse_args(argv)
    if args.standins == []:
        args.standins = list(STANDINS)
    full = dict(spp=[16, 64, 256], trials=8, ref_spp=1024, ref_seeds=8, mi_ref_spp=1024, mi_ref_seeds=8, fd_spp=16384)
    quick = dict(spp=[16], trials=3, ref_spp=256, ref_seeds=4, mi_ref_spp=256, mi_ref_seeds=4, fd_spp=2048)
    for k, v in (quick if args.quick else full).items():
        if getattr(args, k) is None:
            setattr(args, k, v)
    bad = [s for s in args.scenes if not (REPO / "configs" / "validation" / f"{s}.yaml").exists()]
    if bad:
        ap.error(f"--scenes: no configs/validation/{bad[0]}.yaml")
    if args.trials < 3:
        ap.error("--trials: at least 3")
    if min(args.spp) < 1 or args.ref_seeds < 2 or args.mi_ref_seeds < 2 or args.fd_spp < FD_BATCHES:
        ap.error("sample counts must be positive, reference seeds ≥ 2, --fd-spp ≥ 8")
    return args


def main(argv=None):
    args = parse_args(argv)
    if args.standins or args.smooth_cost:
        run_standins(args)
        return
    if args.render_only:
        report = json.loads((args.out / "gradients.json").read_text())
        write_atomic(args.out / "gradients.md", markdown(report))
        log(f"wrote {args.out / 'gradients.md'} from {args.out / 'gradients.json'}")
        return
    t_start = time.perf_counter()
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    report = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "settings": settings,
              "git": git_state(), "machine": None, "scenes": {}, "total_seconds": 0.0}
    for name in args.scenes:
        config = REPO / "configs" / "validation" / f"{name}.yaml"
        t_scene = time.perf_counter()
        log(f"{name}: building the scene")
        b = Bench(config)
        if report["machine"] is None:
            report["machine"] = machine_info(b.variant)
            log(f"variant {b.variant}, {os.cpu_count()} CPU cores")
        W, H = b.scene.resolution
        log(f"{name}: {W}×{H}, max_depth {b.max_depth}, parameter {b.parameter.name}")
        refs, ours_ref, _ = references(b, args)
        eq = [equal_time(b, spp, args, ours_ref) for spp in args.spp]
        shading = {o.name: "smooth" if o.smooth else "flat" for o in b.exp.scene.objects if o.edges}
        check = None
        if args.shading_check and "flat" in shading.values():
            log(f"{name}: shading check, the same references with {', '.join(shading)} smooth-shaded")
            check = references(Bench(config, smooth=True), args)[0]
        report["scenes"][name] = {
            "config": str(config.relative_to(REPO)),
            "config_sha256": hashlib.sha256(b.config_text.encode()).hexdigest(), "config_text": b.config_text,
            "resolution": [W, H], "max_depth": b.max_depth, "parameter": b.parameter.name,
            "shading": shading, "references": refs, "equal_time": eq, "smooth_shading_check": check,
            "seconds": time.perf_counter() - t_scene}
        report["total_seconds"] = time.perf_counter() - t_start
        write_atomic(args.out / "gradients.json", json.dumps(report, indent=1))
        write_atomic(args.out / "gradients.md", markdown(report))
        log(f"{name}: done in {time.perf_counter() - t_scene:.0f} s (total {report['total_seconds']:.0f} s)")
    report["total_seconds"] = time.perf_counter() - t_start
    write_atomic(args.out / "gradients.json", json.dumps(report, indent=1))
    write_atomic(args.out / "gradients.md", markdown(report))
    log(f"wrote {args.out / 'gradients.json'} and {args.out / 'gradients.md'} "
        f"({report['total_seconds'] / 60:.1f} min)")


if __name__ == "__main__":
    main()
