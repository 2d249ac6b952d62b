"""``psdr`` command line: a thin layer over :mod:`psdr_cli.api`.

Every user-facing failure is printed as one ``error: ...`` line on stderr with exit code 2;
an unexpected internal failure prints one line (and the traceback only with ``PSDR_DEBUG=1``).
"""
from __future__ import annotations

import functools
import os
import sys
import time
import warnings
from pathlib import Path
from typing import Optional

import numpy as np
import typer
from typer._click.exceptions import UsageError  # typer vendors click: its usage errors
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from . import __version__, api
from .commands.sweep import RayOptions
from .config.options import with_estimator
from .errors import PsdrError, PsdrWarning
from .support.verdict import describe

app = typer.Typer(
    name="psdr",
    help="Path-space differentiable rendering with guided boundary sampling (Yan et al. 2022).",
    invoke_without_command=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
)
console = Console(stderr=True)
out = Console()


def fail(message: str, code: int = 2):
    console.print(f"[bold red]error:[/] {escape(message)}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def guarded(fn):
    """Turn every exception into one line and a non-zero exit code."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except typer.Exit:
            raise
        except PsdrError as exc:
            fail(str(exc))
        except KeyboardInterrupt:
            console.print("interrupted")
            raise typer.Exit(130)
        except Exception as exc:  # noqa: BLE001
            if os.environ.get("PSDR_DEBUG"):
                raise
            first = str(exc).splitlines()[0] if str(exc) else ""
            fail(f"internal error: {type(exc).__name__}: {first} (set PSDR_DEBUG=1 for a traceback)", 1)
    return wrapper


class Bar:
    """Rich progress bar over samples, shared by the subcommands."""

    def __init__(self, label: str):
        self.label = label
        self.progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                                 TimeElapsedColumn(), TimeRemainingColumn(), console=console, transient=False)
        self.task = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self.task is not None:
            self.progress.__exit__(*exc)

    def start(self, total: int):
        """Show the bar (only once the work is about to begin, so errors before it stay one line)."""
        self.progress.__enter__()
        self.task = self.progress.add_task(self.label, total=total)

    def advance(self, n: int):
        self.progress.advance(self.task, n)


def load_experiment(config: Path):
    """The experiment file, its scene read; warnings (what psdr cannot differentiate) on stderr."""
    return api.load_experiment(config, warn=lambda m: console.print(f"[yellow]warning:[/] {m}", highlight=False,
                                                                     soft_wrap=True))


def version_callback(value: bool):
    if value:
        out.print(f"psdr {__version__}")
        raise typer.Exit()


@app.callback()
def main(ctx: typer.Context,
         version: bool = typer.Option(False, "--version", callback=version_callback, is_eager=True,
                                      help="Print the version and exit.")):
    """Each subcommand reads a YAML experiment file (see docs/config.md)."""
    if ctx.invoked_subcommand is None:
        out.print(ctx.get_help())
        raise typer.Exit(0)


ConfigArg = typer.Argument(..., help="YAML experiment file.", show_default=False)
PortOption = typer.Option(8080, "--port", min=0, max=65535, help="With the viewer: its port (the next free one when taken).")
HostOption = typer.Option("127.0.0.1", "--host", help="With the viewer: the address it listens on (0.0.0.0 shares it).")
ViewsOption = typer.Option(None, "--views", help="Views, e.g. 0,3 or 0-2 (default: all).")
OutOption = typer.Option(None, "--out", help="Output folder (replaces the experiment's 'output').")
RayOption = typer.Option(None, "--ray", metavar="[ADDRESS]",
                         help="One Ray task per run/variant: a local Ray instance, or join 'auto' / 'ray://HOST:PORT' "
                              "(needs pip install 'psdr[ray]').")
RayCpusOption = typer.Option(1, "--ray-cpus", help="With --ray: CPUs (and Dr.Jit threads) per task on the CPU backend.")
RayFilesOption = typer.Option("auto", "--ray-files", help="With --ray: shared (workers write the run folders) or copy "
                              "(workers send their files to the driver); auto: shared locally, copy on a cluster.")


def ray_options(address, cpus: int, files: str):
    """sweep.RayOptions of the --ray options, or None without --ray."""
    return None if address is None else RayOptions(address=address, cpus=cpus, files=files)


@app.command()
@guarded
def render(config: Path = ConfigArg,
           spp: Optional[int] = typer.Option(None, "--spp", help="Samples per pixel (default: estimator.spp)."),
           views: Optional[str] = ViewsOption,
           out_dir: Optional[Path] = OutOption):
    """Render every camera view to EXR (+ PNG preview)."""
    exp = load_experiment(config)
    with Bar("render") as bar:
        res = api.render(exp, spp=spp, views=views, out=out_dir, progress=bar)
    table = Table(title=f"psdr render: {exp.name}")
    for col in ("view", "resolution", "spp", "seconds", "file"):
        table.add_column(col, justify="right" if col != "file" else "left")
    for v, f, s in zip(res.views, res.files, res.seconds):
        table.add_row(str(v), f"{res.resolution[0]}×{res.resolution[1]}", str(res.spp), f"{s:.2f}", str(f))
    out.print(table)
    out.print(f"{len(res.views)} view(s), {res.variant}, total {sum(res.seconds):.2f} s; outputs in {res.folder}")


@app.command()
@guarded
def grad(config: Path = ConfigArg,
         spp: Optional[int] = typer.Option(None, "--spp", help="Samples per pixel of every term (sets estimator.spp, primary_spp and boundary_spp)."),
         interior_spp: Optional[int] = typer.Option(None, "--interior-spp", help="Samples per pixel of the interior term only (default: estimator.spp)."),
         terms: Optional[str] = typer.Option(None, "--terms", help="Terms, e.g. interior,primary,direct,indirect (default: estimator.terms)."),
         views: Optional[str] = ViewsOption,
         fd: Optional[float] = typer.Option(None, "--fd", help="Also compute central finite differences with step H and report the agreement."),
         fd_spp: Optional[int] = typer.Option(None, "--fd-spp", help="Samples per pixel of the finite differences (default: 4 × spp)."),
         sampling: Optional[str] = typer.Option(None, "--sampling", help="Boundary direction sampling: dir, light or mis (default: estimator.sampling)."),
         guiding: Optional[str] = typer.Option(None, "--guiding", help="Boundary guiding: none, grid or kdtree (default: estimator.guiding)."),
         edge_sort: Optional[bool] = typer.Option(None, "--edge-sort/--no-edge-sort", help="Sort edges into chains (default: estimator.edge_sort)."),
         out_dir: Optional[Path] = OutOption):
    """Gradient image dI/dθ per term (interior, primary, direct, indirect) and their total."""
    exp = load_experiment(config)
    exp = with_estimator(exp, sampling=sampling, guiding=guiding, edge_sort=edge_sort,
                         spp=spp, primary_spp=spp, boundary_spp=spp)
    with Bar("grad") as bar:
        res = api.grad(exp, spp=interior_spp, terms=terms, views=views, out=out_dir, fd=fd, fd_spp=fd_spp, progress=bar,
                       warn=lambda m: console.print(f"[yellow]warning:[/] {m}", highlight=False), report=out.print)
    table = Table(title=f"psdr grad: {exp.name} — d/dθ, θ = {res.parameter}")
    for col in ("view", "term", "image sum", "seconds"):
        table.add_column(col, justify="right" if col != "term" else "left")
    for v, secs, sums in zip(res.views, res.seconds, res.sums):
        for t, s in secs.items():
            table.add_row(str(v), t, f"{sums[t]:.5g}" if t in sums else "—", f"{s:.2f}")
        table.add_row(str(v), "[bold]total", f"[bold]{sums['total']:.5g}", f"{sum(secs.values()):.2f}")
    out.print(table)
    for v, a in zip(res.views, res.agreement):
        if a:
            s, b = a["sum"], a["blocks"]
            verdict = "agrees" if a["agrees"] else "DISAGREES"
            out.print(f"view {v}: estimate {s['estimate']:.5g} ± {s['estimate_se']:.2g}, finite differences "
                      f"{s['fd']:.5g} ± {s['fd_se']:.2g} (z = {s['z']:+.2f}); {b['size']}×{b['size']} tiles: "
                      f"{100 * b['within_3se']:.0f}% within 3 SE, max |z| {b['max_abs_z_signal']:.2f} over "
                      f"{b['signal']} signal tiles, correlation {b['correlation']:.3f} — {verdict}")
            out.print(describe(a), markup=False)
    out.print(f"{len(res.views)} view(s), {res.variant}; outputs in {res.folder}")


@app.command("guide-stats")
@guarded
def guide_stats(config: Path = ConfigArg,
                guides: Optional[str] = typer.Option(None, "--guides", help="Guides to build: grid,kdtree (default: estimator.guiding, or both)."),
                views: Optional[str] = typer.Option(None, "--views", help="Views the guides are built for (default: all)."),
                out_dir: Optional[Path] = OutOption):
    """Build the boundary guides with and without edge sorting; table, JSON and plots."""
    exp = load_experiment(config)
    with Bar("guide-stats") as bar:
        res = api.guide_stats(exp, kinds=guides, views=views, out=out_dir, progress=bar)
    table = Table(title=f"psdr guide-stats: {exp.name}")
    for col in ("sorted", "guide", "leaves", "depth", "KiB", "build s", "build / pass", "evals", "norm"):
        table.add_column(col, justify="left" if col in ("sorted", "guide") else "right", no_wrap=True)
    for key, stats in res.guides.items():
        for label, s in stats.items():
            table.add_row("yes" if key == "sorted" else "no", label, str(s["leaves"]), str(s["max_depth"]), f"{s['memory_bytes'] / 1024:.1f}",
                          f"{s['build_seconds']:.2f}", f"{s['build_over_pass']:.2f}", str(s["evaluations"]),
                          f"{s['normalization']:.3g}")
    out.print(table)
    for key, c in res.chains.items():
        out.print(f"{key}: {c['edges']} edges in {c['chains']} chains (mean length {c['mean_chain_length']:.1f}); "
                  f"the Kd-tree pre-splits u1 into that many pieces")
    out.print(f"outputs in {res.folder}")


@app.command()
@guarded
def compare(config: Path = ConfigArg,
            out_dir: Optional[Path] = OutOption,
            ray: Optional[str] = RayOption, ray_cpus: int = RayCpusOption, ray_files: str = RayFilesOption):
    """Equal-time / equal-sample comparison of boundary estimators (the experiment's compare: section)."""
    exp = load_experiment(config)
    opts = ray_options(ray, ray_cpus, ray_files)
    if opts is not None:
        res = api.compare(exp, out=out_dir, progress=lambda label: TaskLine(f"compare {label}"), ray=opts)
    else:
        with Bar("compare") as bar:
            res = api.compare(exp, out=out_dir, progress=bar)
    table = Table(title=f"psdr compare: {exp.name} (reference relMSE ≈ {res.reference_rel_mse:.2g})")
    for col in ("variant", "relMSE", "passes", "build s"):
        table.add_column(col, justify="left" if col == "variant" else "right")
    for r in res.rows:
        table.add_row(r.variant.label, f"{r.rel_mse:.4g}", str(int(np.mean(r.passes))), f"{r.build_seconds:.2f}")
    out.print(table)
    out.print(f"outputs in {res.folder} (compare.md, compare.json, grid.png, one EXR per variant)")


class TaskLine:
    """Progress of one task of a Ray comparison: one line when it ends."""

    def __init__(self, label: str):
        self.label, self.t0 = label, time.monotonic()

    def start(self, total: int, done: int = 0):
        self.t0 = time.monotonic()

    def advance(self, n: int, rel_mse: float | None = None):
        value = f", relMSE {rel_mse:.4g}" if rel_mse is not None else ""
        console.print(f"{self.label}: done after {time.monotonic() - self.t0:.0f} s{value}", highlight=False)


class LossBar(Bar):
    """Progress over iterations with the current loss: a live bar on a terminal; otherwise (output
    redirected to a file or a pipe) one plain line every ``every`` iterations and at the end,
    with iteration, loss, elapsed time and ETA."""

    def __init__(self, label: str, every: int = 10):
        super().__init__(label)
        self.every, self.lines = every, not console.is_terminal
        self.progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                                 TextColumn("loss {task.fields[loss]}"), TimeElapsedColumn(), TimeRemainingColumn(),
                                 console=console, transient=False)

    def start(self, total: int, done: int = 0):
        self.total, self.done, self.first, self.t0 = total, done, done, time.monotonic()
        if self.lines:
            console.print(f"{self.label}: {total - done} iterations to run ({done} done before)", highlight=False)
            return
        self.progress.__enter__()
        self.task = self.progress.add_task(self.label, total=total, completed=done, loss="—")

    def advance(self, n: int, loss: float | None = None):
        self.done += n
        if not self.lines:
            self.progress.update(self.task, advance=n, **({"loss": f"{loss:.5g}"} if loss is not None else {}))
            return
        if self.done % self.every == 0 or self.done >= self.total:
            elapsed = time.monotonic() - self.t0
            eta = elapsed / max(self.done - self.first, 1) * (self.total - self.done)
            console.print(f"{self.label}: iteration {self.done}/{self.total}, loss {loss:.5g}, "
                          f"elapsed {elapsed:.0f} s, ETA {eta:.0f} s", highlight=False)


class RunLines:
    """One progress line per run of a Ray sweep: rows of one live display on a terminal; plain
    lines (as :class:`LossBar`) otherwise."""

    def __init__(self, every: int = 10):
        self.every = every
        self.progress = LossBar("", every).progress

    def __enter__(self):
        if console.is_terminal:
            self.progress.__enter__()
        return self

    def __exit__(self, *exc):
        if console.is_terminal:
            self.progress.__exit__(*exc)

    def row(self, label):
        bar = LossBar(f"{label}" if label else "run", self.every)
        bar.progress = self.progress  # shared display, started once by __enter__
        return bar


@app.command()
@guarded
def optimize(config: Path = ConfigArg,
             resume: bool = typer.Option(False, "--resume", help="Continue from the run's saved state."),
             iterations: Optional[int] = typer.Option(None, "--iterations", help="Total iterations (default: optimize.iterations)."),
             variant: Optional[list[str]] = typer.Option(None, "--variant", help="Run only this variant of optimize.variants (repeatable; default: all)."),
             log_every: int = typer.Option(10, "--log-every", min=1, help="When the output is not a terminal: a progress line every N iterations."),
             ray: Optional[str] = RayOption, ray_cpus: int = RayCpusOption, ray_files: str = RayFilesOption,
             view: bool = typer.Option(False, "--view", help="Watch the run in a web page (needs pip install 'psdr[view]')."),
             port: int = PortOption, host: str = HostOption):
    """Reconstruct an object's shape from images (mini-batches, L1 loss, large steps, checkpoints)."""
    exp = load_experiment(config)
    warn = lambda m: console.print(f"[yellow]warning:[/] {m}", highlight=False)  # noqa: E731
    opts = ray_options(ray, ray_cpus, ray_files)
    if view and opts is not None:
        raise PsdrError("--view and --ray: the viewer watches a loop running in this process; drop one")
    label_of = lambda label: f"optimize {label}" if label else "optimize"  # noqa: E731
    if opts is not None:  # one line per run while they run side by side; the summaries once all have ended
        with RunLines(log_every) as lines:
            print_runs(api.optimize_variants(exp, variant, iterations, resume, warn=warn, ray=opts, report=out.print,
                                             progress=lambda label: lines.row(label_of(label))))
    else:
        viewer = live_viewer(host, port, warn) if view else None
        try:
            print_runs(api.optimize_variants(exp, variant, iterations, resume, warn=warn, report=out.print,
                                             progress=lambda label: LossBar(label_of(label), log_every),
                                             observer=viewer))
        finally:
            if viewer:
                viewer.close()
    where = f"{exp.run_dir}/<variant>/" if exp.optimize.variants else f"{exp.run_dir}/"
    out.print(f"outputs in {where} (checkpoints/, previews/, log.csv, loss.png); "
              f"evaluate with: psdr evaluate {config}")


def print_runs(runs):
    """One summary line per run as it ends (and the time budget's stop); exit 130 on an interrupted run."""
    for label, res in runs:
        if res.interrupted:
            raise typer.Exit(130)
        first = f"{res.losses[0]:.5g}" if res.losses else "—"
        last = f"{res.losses[-1]:.5g}" if res.losses else "—"
        out.print(f"{label + ': ' if label else ''}{res.iterations} iterations (this run: {len(res.losses)}, "
                  f"resumed from {res.resumed_from}); loss {first} → {last}; final mesh {res.final}")
        if res.budget_stop:
            out.print(f"{label + ': ' if label else ''}the time budget (optimize.seconds) ended the run after "
                      f"{res.iterations} iterations ({res.seconds:.1f} s of optimisation)")


@app.command()
@guarded
def evaluate(paths: list[str] = typer.Argument(None, help="Experiment file, meshes (.ply/.obj) and/or `psdr optimize` run folders."),
             reference: Optional[Path] = typer.Option(None, "--reference", help="Reference mesh (default: evaluate.reference, or the run's reference.ply)."),
             samples: Optional[int] = typer.Option(None, "--samples", help="Points sampled per surface (default 100000)."),
             json_out: Optional[Path] = typer.Option(None, "--json", help="Also write the results as JSON."),
             report: Optional[Path] = typer.Option(None, "--report", help="Folder for a side-by-side report of the runs (default with optimize.variants: the experiment's run folder)."),
             align: str = typer.Option("auto", "--align", help="Held-out views: fit each held-out camera's pose to its photograph before scoring (auto: when the run refined its cameras; on; off)."),
             relight: Optional[Path] = typer.Option(None, "--relight", help="A camera dataset of the object under other light (the training capture's world frame): score the runs relit by --envmap from its cameras."),
             envmap: Optional[Path] = typer.Option(None, "--envmap", help="With --relight: the lat-long EXR environment map of that light."),
             envmap_scale: float = typer.Option(1.0, "--envmap-scale", help="With --relight: the map's radiance scale."),
             max_depth: Optional[int] = typer.Option(None, "--max-depth", help="Held-out views: render paths of this many segments (default: the run's scene.max_depth; e.g. the depth the photographs' light needs)")):
    """Normalised Chamfer and Hausdorff distances to a reference mesh (tables, JSON, plots)."""
    if align not in ("auto", "on", "off"):
        raise PsdrError(f"--align: expected auto, on or off, got '{align}'")
    if (relight is None) != (envmap is None):
        raise PsdrError("--relight and --envmap: give both (the photographs under the other light, and that light)")
    if not (envmap_scale > 0 and envmap_scale < 1e30):
        raise PsdrError(f"--envmap-scale: expected a number > 0, got {envmap_scale}")
    light = api.Relight(relight, envmap, envmap_scale) if relight is not None else None
    with Bar("evaluate") as bar:
        res = api.evaluate(paths, reference, samples=samples, json_out=json_out, report=report, progress=bar,
                           align=align, relight=light, max_depth=max_depth)
    if light is not None:
        print_relit(res)
        return
    if hasattr(res, "folders"):  # a camera dataset: held-out views
        print_held_out(res)
        return
    table = Table(title=f"psdr evaluate: reference {res.reference}")
    for col in ("mesh", "iteration", "seconds", "Chamfer-L1", "Chamfer-L2²", "Hausdorff"):
        table.add_column(col, justify="left" if col == "mesh" else "right")
    for r in res.rows:
        table.add_row(Path(r["mesh"]).name if r["run"] else r["mesh"], "" if r["iteration"] is None else str(r["iteration"]),
                      "" if r["seconds"] is None else f"{r['seconds']:.1f}", f"{r['chamfer_l1']:.5f}",
                      f"{r['chamfer_l2']:.3e}", f"{r['hausdorff']:.4f}")
    out.print(table)
    nf = res.noise_floor
    out.print(f"sampling noise floor (reference vs itself): Chamfer-L1 {nf['chamfer_l1']:.5f}, "
              f"Chamfer-L2² {nf['chamfer_l2']:.2e}, Hausdorff {nf['hausdorff']:.4f}")
    for p in res.plots:
        out.print(f"plot: {p}")
    if res.report:
        out.print(f"report: {res.report} (evaluate.md, chamfer.png, meshes.png, evaluate.json)")


def print_relit(res):
    """The table of ``psdr evaluate --relight``."""
    table = Table(title=f"psdr evaluate: {res.experiment.name} relit")
    for col in ("mesh", "iteration", "views", "PSNR-H", "PSNR-L", "SSIM", "mask IoU"):
        table.add_column(col, justify="left" if col == "mesh" else "right")
    for r in res.rows:
        table.add_row(Path(r["mesh"]).name, str(r["iteration"]), str(r["views"]), f"{r['psnr_h']:.2f}",
                      f"{r['psnr_l']:.2f}", f"{r['ssim']:.4f}", f"{r['iou']:.4f}")
    out.print(table)
    out.print("each render scaled per channel by least squares in the mask before scoring (light × albedo is ambiguous)")
    for folder in res.folders:
        out.print(f"report: {folder} (relight.md, relight.json, a target | render | error strip per view)")


def print_held_out(res):
    """The table of ``psdr evaluate`` on a dataset experiment (held-out views)."""
    table = Table(title=f"psdr evaluate: held-out views of {res.experiment.name}")
    cols = ("mesh", "iteration", "views", "max depth", "poses", "PSNR", "PSNR mask", "SSIM", "SSIM mask", "mask IoU",
            "PSNR as given", "Chamfer-L1", "depth err", "normal °")
    for col in cols:
        table.add_column(col, justify="left" if col in ("mesh", "poses") else "right")
    fmt = lambda v, f: "—" if v is None else format(v, f)  # noqa: E731
    for r in res.rows:
        table.add_row(Path(r["mesh"]).name, str(r["iteration"]), str(r["views"]), str(r.get("max_depth", "—")),
                      r.get("poses", "as given"),
                      fmt(r["psnr"], ".2f"), fmt(r["psnr_mask"], ".2f"), fmt(r["ssim"], ".4f"),
                      fmt(r["ssim_mask"], ".4f"), fmt(r["iou"], ".4f"), fmt(r.get("as_given", r)["psnr"], ".2f"),
                      fmt(r.get("chamfer_l1"), ".5f"), fmt(r.get("depth_error"), ".2e"), fmt(r.get("normal_deg"), ".2f"))
    out.print(table)
    if any(r.get("poses") == "aligned" for r in res.rows):
        out.print("poses 'aligned': the run refined its cameras, so each held-out camera was fitted to its photograph "
                  "with the recovered scene fixed before scoring ('PSNR as given': without that fit)")
    for folder in res.folders:
        out.print(f"report: {folder} (held_out.md, held_out.json, a target | render | error strip per view)")


@app.command()
@guarded
def table2(configs: list[Path] = typer.Argument(..., help="Experiment files whose `psdr optimize` runs to report."),
           out_file: Path = typer.Option(Path("table2.md"), "--out", help="Markdown file to write.")):
    """The paper's Table 2 for finished optimize runs: configuration, per-iteration time split
    (guiding, rendering, post-processing) and guide memory, with the paper's rows for reference."""
    path = api.table2([load_experiment(c) for c in configs], out_file)
    out.print(path.read_text())
    out.print(f"written: {path}")


@app.command()
@guarded
def export(source: Path = typer.Argument(..., help="A `psdr optimize` run folder, or a .ply/.obj mesh.", show_default=False),
           out_dir: Optional[Path] = typer.Option(None, "--out", help="Output folder (default: the run's export/, or <mesh>_export/)."),
           texture: Optional[Path] = typer.Option(None, "--texture", help="A mesh file's albedo texture (PNG/JPEG/EXR), looked up at its UVs.")):
    """Write a reconstruction as OBJ + MTL + PNG and binary glTF (.glb), with the rotated
    environment map of a run that recovered its rotation."""
    warn = lambda m: console.print(f"[yellow]note:[/] {escape(m)}", highlight=False, soft_wrap=True)  # noqa: E731
    res = api.export(source, out_dir, texture, warn=warn)
    out.print(f"exported to {res.folder}: {', '.join(p.name for p in res.files)}")


def live_viewer(host: str, port: int, warn):
    """The viewer of ``psdr optimize --view``, its address printed."""
    viewer = api.live_viewer(host, port, warn)
    if viewer.url:
        out.print(f"viewer: {viewer.url} (the Pause box holds the run between iterations)")
    return viewer


@app.command()
@guarded
def view(path: Path = typer.Argument(..., help="A `psdr optimize` run folder (finished or running), or a .ply/.obj mesh.", show_default=False),
         port: int = PortOption, host: str = HostOption,
         seconds: Optional[float] = typer.Option(None, "--seconds", hidden=True, help="Stop after S seconds (tests).")):
    """Show a run folder (checkpoints on a slider, cameras, loss, previews) or a mesh in a web
    page, read-only, until Ctrl-C."""
    warn = lambda m: console.print(f"[yellow]warning:[/] {escape(m)}", highlight=False, soft_wrap=True)  # noqa: E731
    api.view(path, host, port, seconds, warn=warn, ready=lambda url: out.print(f"viewer: {url} (Ctrl-C to stop)"))


def ray_flag(argv: list) -> list:
    """``--ray`` takes an optional address: without one (end of the line, an option or the
    experiment file next) it means a local Ray instance, ``--ray local``."""
    out = list(argv)
    for i in [i for i, a in enumerate(out) if a == "--ray"][::-1]:
        if i + 1 == len(out) or not RayOptions.is_address(out[i + 1]):
            out.insert(i + 1, "local")
    return out


def run(args: list[str] | None = None) -> int:
    """Console-script entry point. Usage errors (unknown option or subcommand, a missing argument,
    an option value of the wrong type) are printed as one ``error:`` line with exit code 2, like
    every other error; ``--help`` prints the usual help."""
    warnings.showwarning = show_warning
    try:
        code = app(args=ray_flag(sys.argv[1:] if args is None else args), prog_name="psdr",
                   standalone_mode=False)
    except UsageError as exc:
        command = exc.ctx.command_path if exc.ctx is not None else "psdr"
        message = " ".join(exc.format_message().split())
        console.print(f"[bold red]error:[/] {escape(f'{command}: {message} (see {command} --help)')}",
                      highlight=False, soft_wrap=True)
        return 2
    except typer.Abort:
        console.print("interrupted")
        return 130
    return code if isinstance(code, int) else 0


def show_warning(message, category, filename, lineno, file=None, line=None):
    """psdr's warnings (e.g. a torn log.csv being read) as one ``warning:`` line; other libraries'
    warnings (numpy overflow in a cast, ...) only with ``PSDR_DEBUG=1``."""
    if not issubclass(category, PsdrWarning) and not os.environ.get("PSDR_DEBUG"):
        return
    console.print(f"[yellow]warning:[/] {escape(str(message))}", highlight=False, soft_wrap=True)


if __name__ == "__main__":
    sys.exit(run())
