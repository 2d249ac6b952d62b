"""Python API behind the CLI: each function runs one subcommand and returns what it wrote."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import backend, io
from .config import Experiment
from .errors import PsdrError


def setup(exp: Experiment) -> str:
    """Activate the experiment's Mitsuba variant (``auto``: CUDA when present, else LLVM)."""
    return backend.select_variant(exp.variant)


def parse_views(views, count: int) -> list[int]:
    """View indices from None (all), a list of ints, or a string like '0,3' or '0-2,5'."""
    if views is None:
        return list(range(count))
    if isinstance(views, str):
        out = []
        for part in filter(None, (p.strip() for p in views.split(","))):
            try:
                if "-" in part:
                    a, b = (int(x) for x in part.split("-", 1))
                    out.extend(range(a, b + 1))
                else:
                    out.append(int(part))
            except ValueError:
                raise PsdrError(f"--views: cannot read '{part}' (expected indices like 0,3 or 0-2)") from None
        views = out
    bad = [v for v in views if not 0 <= v < count]
    if bad or not views:
        raise PsdrError(f"--views: view {bad[0] if bad else '(none)'} does not exist "
                        f"(the experiment has views 0..{count - 1})")
    return sorted(set(views))


@dataclass
class RenderResult:
    folder: Path
    views: list
    files: list = field(default_factory=list)
    seconds: list = field(default_factory=list)
    spp: int = 0
    resolution: tuple = (0, 0)
    variant: str = ""


def render(exp: Experiment, spp: int | None = None, views=None, out: Path | None = None,
           progress=None) -> RenderResult:
    """Render the experiment's views to ``<output>/<name>/render/view_XXX.exr`` (+ PNG previews).

    ``out`` replaces the experiment's ``output`` folder.

    ``progress`` is an optional object with ``start(total_samples)`` and ``advance(n)``.
    """
    from .render import render_view
    from .scene import build_scene

    spp = exp.estimator.spp if spp is None else spp
    if spp < 1:
        raise PsdrError(f"--spp: expected a positive number of samples per pixel, got {spp}")
    variant = setup(exp)
    scene = build_scene(exp)
    views = parse_views(views, len(exp.scene.cameras))
    folder = (Path(out).resolve() / exp.name if out else exp.run_dir) / "render"
    W, H = scene.resolution
    result = RenderResult(folder, views, spp=spp, resolution=(W, H), variant=variant)
    if progress:
        progress.start(len(views) * spp)
    for v in views:
        t0 = time.perf_counter()
        image = render_view(scene, v, spp, seed=exp.seed, progress=progress.advance if progress else None)
        result.seconds.append(time.perf_counter() - t0)
        cam = exp.scene.cameras[v]
        header = {"psdr.experiment": str(exp.file), "psdr.view": str(v), "psdr.spp": str(spp),
                  "psdr.seed": str(exp.seed), "psdr.camera": {"origin": cam.origin, "target": cam.target,
                                                              "up": cam.up, "fov": cam.fov}}
        exr = folder / f"view_{v:03d}.exr"
        io.write_rgb_exr(exr, image, header)
        io.write_preview(exr.with_suffix(".png"), image)
        result.files.append(exr)
    return result


@dataclass
class GradResult:
    folder: Path
    views: list
    parameter: str = ""
    files: list = field(default_factory=list)
    seconds: list = field(default_factory=list)      # per view: {term: seconds}
    sums: list = field(default_factory=list)         # per view: {term: image sum}
    agreement: list = field(default_factory=list)    # per view: FD agreement (with --fd)
    variant: str = ""


def with_estimator(exp: Experiment, **overrides) -> Experiment:
    """The experiment with estimator keys replaced (``None`` values are ignored); values are
    checked like the YAML keys: ``sampling`` dir|light|mis, ``guiding`` none|grid|kdtree."""
    from dataclasses import replace
    allowed = {"sampling": ("dir", "light", "mis"), "guiding": ("none", "grid", "kdtree")}
    changes = {k: v for k, v in overrides.items() if v is not None}
    for key, value in changes.items():
        if key in allowed and value not in allowed[key]:
            raise PsdrError(f"--{key.replace('_', '-')}: expected one of {', '.join(allowed[key])}, got '{value}'")
    return replace(exp, estimator=replace(exp.estimator, **changes)) if changes else exp


def edge_list(scene, estimator, sort: bool):
    """The scene's boundary edges, sorted into chains with the experiment's chain parameters."""
    from .estimators.boundary_sampling import BoundaryEdges
    return BoundaryEdges.from_scene(scene, sort, estimator.chains.max_turn, estimator.chains.max_length)


def prepare_gradient(exp: Experiment, spp: int | None = None, scene=None):
    """(scene, θ parameter, boundary edges, settings) of an experiment, variant activated."""
    from .gradient import Settings
    from .parameters import Parameter
    from .scene import build_scene

    if exp.parameter is None:
        raise PsdrError(f"{exp.file}: parameter: missing (expected e.g. {{object: NAME, kind: translate, axis: [1, 0, 0]}})")
    if spp is not None and spp < 1:
        raise PsdrError(f"--spp: expected a positive number of samples per pixel, got {spp}")
    setup(exp)
    scene = scene or build_scene(exp)
    if exp.parameter.camera is not None:  # every surface's discontinuities move in the image
        from .camera_motion import check_camera_motion, with_all_edges
        with_all_edges(scene)
        check_camera_motion(scene, exp.parameter.camera)
    settings = Settings.from_experiment(exp, spp)
    edges = edge_list(scene, exp.estimator, settings.edge_sort)
    return scene, Parameter(scene, exp.parameter), edges, settings


def gradient_images(exp: Experiment, view: int = 0, terms=None, spp: int | None = None, min_passes: int = 1,
                    scene=None, progress=None) -> dict:
    """Forward-mode gradient images dI/dθ of one view, without writing anything.

    Returns ``{term: TermEstimate}`` for the requested terms (default: ``estimator.terms``);
    each estimate holds the mean image (H, W, 3), the per-pass images and the seconds spent."""
    from .gradient import forward_gradient, make_guides

    scene, parameter, edges, settings = prepare_gradient(exp, spp, scene)
    terms = parse_terms(terms) or exp.estimator.terms
    guides = make_guides(scene, edges, [view], terms, settings)
    return {t: forward_gradient(scene, edges, parameter, view, t, settings, min_passes, progress, guides)
            for t in terms}


def parse_terms(terms) -> tuple:
    from .gradient import TERMS
    if terms is None:
        return None
    names = [t.strip() for t in terms.split(",")] if isinstance(terms, str) else list(terms)
    bad = [t for t in names if t not in TERMS]
    if bad or not names:
        raise PsdrError(f"--terms: unknown term '{bad[0] if bad else ''}' (expected a comma-separated "
                        f"subset of {','.join(TERMS)})")
    return tuple(t for t in TERMS if t in names)


#: Independent batches of the estimate and of the finite differences behind the --fd statistics.
FD_BATCHES = 8


def grad(exp: Experiment, spp: int | None = None, terms=None, views=None, out: Path | None = None,
         fd: float | None = None, fd_spp: int | None = None, progress=None, warn=None) -> GradResult:
    """Gradient images of every requested view to ``<output>/<name>/grad/view_XXX.exr``.

    Channels: the render (R, G, B), one group per term (``interior.R`` …) and ``total.*``; with
    ``fd = h`` also central finite differences ``fd.*`` (common random numbers, 8 batches of
    ``fd_spp`` samples per pixel in total, default 4 × the interior spp) and the agreement
    statistics. PNG previews use a diverging colour map shared by all terms."""
    from .gradient import forward_gradient, make_guides
    from .reference import agreement, finite_difference
    from .render import render_view

    if fd is not None and not fd > 0:
        raise PsdrError(f"--fd: expected a positive step size, got {fd}")
    if fd_spp is not None and fd_spp < FD_BATCHES:
        raise PsdrError(f"--fd-spp: expected at least {FD_BATCHES} samples per pixel ({FD_BATCHES} batches), got {fd_spp}")
    terms = parse_terms(terms) or exp.estimator.terms
    views = parse_views(views, len(exp.scene.cameras))
    scene, parameter, edges, settings = prepare_gradient(exp, spp)
    variant = setup(exp)
    from .shading import smooth_warning
    if smooth_warning(scene) and warn:
        warn(smooth_warning(scene))
    fd_spp = fd_spp or 4 * settings.spp
    min_passes = FD_BATCHES if fd else 1
    folder = (Path(out).resolve() / exp.name if out else exp.run_dir) / "grad"
    result = GradResult(folder, views, parameter.name, variant=variant)
    if progress:
        per_view = sum(settings.samples(t) for t in terms) + (2 * fd_spp if fd else 0)
        progress.start(len(views) * per_view)
    for v in views:
        t0 = time.perf_counter()
        guides = make_guides(scene, edges, [v], terms, settings)
        guide_seconds = time.perf_counter() - t0
        estimates = {t: forward_gradient(scene, edges, parameter, v, t, settings, min_passes,
                                         progress.advance if progress else None, guides) for t in terms}
        image = estimates["interior"].primal if "interior" in estimates else \
            render_view(scene, v, settings.spp, seed=exp.seed)
        total = sum(e.gradient for e in estimates.values())
        channels = {"R": image[..., 0], "G": image[..., 1], "B": image[..., 2]}
        for name, g in [(t, e.gradient) for t, e in estimates.items()] + [("total", total)]:
            for c, ch in enumerate("RGB"):
                channels[f"{name}.{ch}"] = g[..., c]
        header = {"psdr.experiment": str(exp.file), "psdr.view": str(v), "psdr.parameter": parameter.name,
                  "psdr.terms": ",".join(terms), "psdr.sampling": settings.sampling,
                  "psdr.guiding": settings.guiding, "psdr.edge_sort": str(settings.edge_sort),
                  "psdr.guide_seconds": f"{guide_seconds:.3f}",
                  "psdr.spp": {t: str(settings.samples(t)) for t in terms},
                  "psdr.seconds": {t: f"{e.seconds:.3f}" for t, e in estimates.items()}}
        stats = None
        if fd:
            batches = finite_difference(scene, parameter, v, fd, fd_spp, seed=exp.seed, batches=FD_BATCHES,
                                        progress=progress.advance if progress else None)
            fd_image = np.mean(batches, axis=0)
            for c, ch in enumerate("RGB"):
                channels[f"fd.{ch}"] = fd_image[..., c]
            stats = agreement([(e.passes, e.weights) for e in estimates.values()], batches)
            header["psdr.fd_h"] = str(fd)
            header["psdr.fd_spp"] = str(fd_spp)
        exr = folder / f"view_{v:03d}.exr"
        io.write_exr(exr, {k: np.asarray(x, np.float32) for k, x in channels.items()}, header)
        scale = float(np.percentile(np.abs(total.mean(-1)), 99.5)) or 1.0
        io.write_preview(folder / f"view_{v:03d}.png", image)
        previews = [(t, e.gradient) for t, e in estimates.items()] + [("total", total)]
        if fd:
            previews.append(("fd", fd_image))
        for name, g in previews:
            io.write_gradient_preview(folder / f"view_{v:03d}_{name}.png", g, scale)
        result.files.append(exr)
        result.seconds.append({**({"guiding": guide_seconds} if guides.all() else {}),
                               **{t: e.seconds for t, e in estimates.items()}})
        result.sums.append({**{t: float(e.gradient.sum()) for t, e in estimates.items()}, "total": float(total.sum())})
        result.agreement.append(stats)
    io.write_json(folder / "summary.json", {
        "experiment": str(exp.file), "parameter": result.parameter, "variant": variant, "terms": list(terms),
        "spp": {t: settings.samples(t) for t in terms}, "sampling": settings.sampling, "fd_h": fd,
        "guiding": settings.guiding, "edge_sort": settings.edge_sort,
        "views": [{"view": v, "file": str(f), "seconds": s, "sums": m, "fd_agreement": a}
                  for v, f, s, m, a in zip(views, result.files, result.seconds, result.sums, result.agreement)]})
    return result


@dataclass
class GuideStatsResult:
    folder: Path
    guides: dict = field(default_factory=dict)     # {"sorted|unsorted": {label: stats}}
    chains: dict = field(default_factory=dict)     # {"sorted|unsorted": chain stats}
    plots: list = field(default_factory=list)


def guide_stats(exp: Experiment, kinds=None, views=None, out: Path | None = None, progress=None) -> GuideStatsResult:
    """Build the boundary guides of an experiment with and without edge sorting and report them.

    ``kinds``: guides to build (default: ``estimator.guiding``, or both grid and kdtree when it is
    ``none``). Writes ``guide_stats.json``, ``target_u1.png`` per technique (x^B and the target
    along u1, unsorted vs sorted: the paper's Fig. 5) and ``leaves_<kind>_<technique>.png``
    (leaf boundaries in the plane u2.y = ½) to ``<output>/<name>/guide_stats/``."""
    from . import plots
    from .guiding.stats import chain_stats, guide_report, target_curve
    from .scene import build_scene

    variant = setup(exp)
    kinds = kinds or ([exp.estimator.guiding] if exp.estimator.guiding != "none" else ["grid", "kdtree"])
    if isinstance(kinds, str):
        kinds = [k.strip() for k in kinds.split(",") if k.strip()]
    bad = [k for k in kinds if k not in ("grid", "kdtree")]
    if bad:
        raise PsdrError(f"--guides: unknown guide '{bad[0]}' (expected grid and/or kdtree)")
    scene = build_scene(exp)
    views = parse_views(views, len(exp.scene.cameras))
    terms = exp.estimator.terms
    max_depth = exp.scene.max_depth
    techniques = [t for t in ("light", "dir") if "direct" in terms and (exp.estimator.sampling in (t, "mis"))]
    if "indirect" in terms and max_depth >= 3:
        techniques.append("indirect")
    if not techniques:
        raise PsdrError(f"{exp.file}: estimator.terms: guides serve the direct and indirect terms; "
                        f"none of them is requested")
    folder = (Path(out).resolve() / exp.name if out else exp.run_dir) / "guide_stats"
    result = GuideStatsResult(folder)
    curves = {t: {} for t in techniques}
    if progress:
        progress.start(2 * (len(kinds) * len(techniques) + len(techniques)))
    for sort in (False, True):
        key = "sorted" if sort else "unsorted"
        edges = edge_list(scene, exp.estimator, sort)
        if edges.count == 0:
            raise PsdrError(f"{exp.file}: scene.objects: no object has boundary edges (edges: true)")
        result.chains[key] = chain_stats(edges)
        stats, guides = guide_report(scene, edges, views, kinds, techniques, max_depth, exp.estimator, exp.seed)
        result.guides[key] = stats
        if progress:
            progress.advance(len(kinds) * len(techniques))
        for t in techniques:
            curves[t][f"{key} edges"] = target_curve(scene, edges, views, t, max_depth, seed=exp.seed)
            if progress:
                progress.advance(1)
        for label, g in guides.items():
            kind, t = label.split("/")
            png = folder / f"leaves_{kind}_{t}_{key}.png"
            centre = 0.5 * (g.lo + g.hi)
            c = float(centre[np.argmax(g.mass), 0]) if g.total > 0 else 0.5
            window = (max(0.0, c - 0.025), min(1.0, c + 0.025))  # around the heaviest leaf
            plots.leaf_slice(png, g.lo, g.hi, g.pdf_np(centre), u1_range=window,
                             title=f"{kind} guide, {t} ({key} edges): {g.stats.leaves} leaves; slice u2.y = ½, "
                                   f"u1 ∈ [{window[0]:.3f}, {window[1]:.3f}]")
            result.plots.append(png)
    for t in techniques:
        png = folder / f"target_u1_{t}.png"
        plots.target_along_u1(png, curves[t], title=f"{exp.name}: {t} target along u1")
        result.plots.append(png)
    io.write_json(folder / "guide_stats.json", {
        "experiment": str(exp.file), "variant": variant, "views": views, "sampling": exp.estimator.sampling,
        "epsilon": exp.estimator.guide_epsilon, "chains": result.chains, "guides": result.guides,
        "plots": [str(p) for p in result.plots]})
    return result


def optimize(exp: Experiment, iterations: int | None = None, resume: bool = False, progress=None, warn=print):
    """Run ``psdr optimize`` (see :mod:`psdr_cli.optimize`); returns an OptimizeResult."""
    from .optimize import optimize as run
    return run(exp, iterations=iterations, resume=resume, progress=progress, warn=warn)


@dataclass
class EvaluateResult:
    reference: Path
    rows: list = field(default_factory=list)       # {mesh, iteration, seconds, chamfer_l1, chamfer_l2, hausdorff}
    noise_floor: dict = field(default_factory=dict)
    plots: list = field(default_factory=list)
    report: Path | None = None


def evaluate(reference: Path, paths, samples: int = 100_000, seed: int = 0, json_out: Path | None = None,
             progress=None, report: Path | None = None, labels: list | None = None, title: str = "") -> EvaluateResult:
    """Chamfer/Hausdorff distances of meshes (or of every checkpoint of run folders) to
    ``reference``; a run folder also gets ``chamfer.png`` (distance against iteration and time)."""
    from dataclasses import asdict
    from . import evaluate as ev
    from . import plots

    if samples < 100:
        raise PsdrError(f"--samples: expected at least 100 points, got {samples}")
    ref = ev.load(reference)
    jobs = []  # (label, path, iteration, seconds, run folder)
    for p in map(Path, paths):
        if p.is_dir():
            secs = ev.run_seconds(p)
            jobs += [(str(path), path, i, secs.get(i, 0.0 if i == 0 else None), p) for i, path in ev.run_checkpoints(p)]
        else:
            jobs.append((str(p), p, None, None, None))
    if not jobs:
        raise PsdrError("evaluate: no meshes given (expected mesh files or `psdr optimize` run folders)")
    result = EvaluateResult(Path(reference), noise_floor=asdict(ev.noise_floor(ref, samples, seed)))
    if progress:
        progress.start(len(jobs))
    for label, path, iteration, seconds, run in jobs:
        d = ev.distance(ev.load(path), ref, samples, seed)
        result.rows.append({"mesh": label, "run": str(run) if run else None, "iteration": iteration,
                            "seconds": seconds, **asdict(d)})
        if progress:
            progress.advance(1)
    for run in sorted({r["run"] for r in result.rows if r["run"]}):
        rows = [r for r in result.rows if r["run"] == run]
        png = Path(run) / "chamfer.png"
        it = [r["iteration"] for r in rows]
        timed = [r for r in rows if r["seconds"] is not None]
        plots.chamfer(png, it, [r["chamfer_l1"] for r in rows], [r["seconds"] for r in timed],
                      [r["chamfer_l1"] for r in timed], result.noise_floor["chamfer_l1"])
        result.plots.append(png)
    if json_out:
        io.write_json(Path(json_out), {"reference": str(reference), "samples": samples, "seed": seed,
                                       "noise_floor": result.noise_floor, "meshes": result.rows})
    if report:
        runs = [Path(p) for p in paths if Path(p).is_dir()]
        result.report = write_run_report(Path(report), ref, runs, labels or [p.name for p in runs], result, title)
    return result


def write_run_report(folder: Path, ref, runs: list, labels: list, result: EvaluateResult, title: str = "") -> Path:
    """Side-by-side report of several runs in ``folder``: ``chamfer.png`` (Chamfer against
    iteration and time, one line per run), ``meshes.png`` (reference and final meshes, neutral
    shading, final Chamfer-L1 under each), ``evaluate.md`` (final distances and the Table 2 time
    split per run), ``evaluate.json`` and a copy of each final mesh as ``<label>.ply``."""
    import shutil
    from . import evaluate as ev
    from . import plots
    backend.select_variant("auto")  # the mesh pictures render with Mitsuba
    folder.mkdir(parents=True, exist_ok=True)
    series, panels, table, summary = {}, [("reference", ev.mesh_view(*ref, ref[0]))], [], []
    for run, label in zip(runs, labels):
        rows = [r for r in result.rows if r["run"] == str(run)]
        series[label] = ([r["iteration"] for r in rows], [r["seconds"] for r in rows], [r["chamfer_l1"] for r in rows])
        last, s = rows[-1], ev.run_summary(run)
        panels.append((f"{label}\nChamfer-L1 {last['chamfer_l1']:.4f}", ev.mesh_view(*ev.load(last["mesh"]), ref[0])))
        with io.atomic_path(folder / f"{label}.ply") as tmp:
            shutil.copyfile(last["mesh"], tmp)
        summary.append({"label": label, "run": str(run), "final": last, **s})
        table.append(f"| {label} | {s['iterations']} | {s['vertices']} | {s['seconds']:.0f} | {last['chamfer_l1']:.4f} | "
                     f"{last['chamfer_l2']:.2e} | {last['hausdorff']:.3f} | {s['guide_bytes'] / 1024:.0f} KiB | "
                     f"{s['seconds_guiding']:.3f} | {s['seconds_rendering']:.3f} | {s['seconds_post']:.3f} |")
    floor = result.noise_floor["chamfer_l1"]
    plots.chamfer_runs(folder / "chamfer.png", series, floor, title)
    plots.image_grid(folder / "meshes.png", panels, title)
    header = ["| run | iterations | vertices | optimisation s | Chamfer-L1 | Chamfer-L2² | Hausdorff | guide memory | "
              "guiding s/it | render s/it | post s/it |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    with io.atomic_path(folder / "evaluate.md") as tmp:
        Path(tmp).write_text("\n".join(header + table) + f"\n\nSampling noise floor (Chamfer-L1): {floor:.5f}\n")
    io.write_json(folder / "evaluate.json", {"noise_floor": result.noise_floor, "runs": summary})
    with io.atomic_path(folder / "reference.ply") as tmp:
        shutil.copyfile(result.reference, tmp)
    return folder


@dataclass
class CompareResult:
    folder: Path
    rows: list = field(default_factory=list)     # psdr_cli.compare.Row
    reference_rel_mse: float = 0.0


def compare(exp: Experiment, out: Path | None = None, progress=None) -> CompareResult:
    """Run the experiment's ``compare:`` section (see :mod:`psdr_cli.compare`); writes
    ``compare.json``, ``compare.md``, ``grid.png`` and one EXR per variant to
    ``<output>/<name>/compare/``."""
    from . import plots
    from .compare import Comparison
    cfg = exp.compare
    if cfg is None:
        raise PsdrError(f"{exp.file}: compare: missing (expected variants: [{{label: ..., guiding: ...}}, ...])")
    if exp.parameter is None:
        raise PsdrError(f"{exp.file}: parameter: missing (compare needs the scalar θ of the gradient)")
    if cfg.view >= len(exp.scene.cameras):
        raise PsdrError(f"{exp.file}: compare.view: view {cfg.view} does not exist (0..{len(exp.scene.cameras) - 1})")
    setup(exp)
    folder = (Path(out).resolve() / exp.name if out else exp.run_dir) / "compare"
    c = Comparison(exp, cfg.terms, cfg.view)
    if progress:
        progress.start(len(cfg.variants) + 1)
    ref, noise, ref_s = c.reference(cfg.reference_passes)
    if progress:
        progress.advance(1)
    result = CompareResult(folder, reference_rel_mse=noise)
    for v in cfg.variants:
        row = c.measure(v, ref, noise, cfg.budget_seconds, cfg.trials)
        result.rows.append(row)
        io.write_rgb_exr(folder / f"{v.label.replace('/', '_').replace(' ', '_')}.exr", row.image,
                         {"psdr.variant": v.label, "psdr.rel_mse": f"{row.rel_mse:.6g}"})
        if progress:
            progress.advance(1)
    io.write_rgb_exr(folder / "reference.exr", ref, {"psdr.passes": str(cfg.reference_passes)})
    plots.gradient_grid(folder / "grid.png", ref, [(r.variant.label, r.image, r.rel_mse) for r in result.rows],
                        f"{exp.name}: {'+'.join(cfg.terms)} gradient, "
                        + (f"{cfg.budget_seconds:g} s per variant" if any(v.passes is None for v in cfg.variants)
                           else "equal samples"))
    table = ["| variant | guiding | sampling | sorted | budget | relMSE | passes | build s | build / pass |",
             "|---|---|---|---|---|---:|---:|---:|---:|"]
    for r in result.rows:
        v = r.variant
        table.append(f"| {v.label} | {v.guiding} | {v.sampling} | {'yes' if v.edge_sort else 'no'} | "
                     f"{f'{v.passes} passes' if v.passes else f'{cfg.budget_seconds:g} s'} | {r.rel_mse:.4g} | "
                     f"{int(np.mean(r.passes))} | {r.build_seconds:.2f} | {r.build_over_pass:.1f} |")
    with io.atomic_path(folder / "compare.md") as tmp:
        Path(tmp).write_text("\n".join(table) + "\n")
    io.write_json(folder / "compare.json", {
        "experiment": str(exp.file), "terms": list(cfg.terms), "view": cfg.view, "budget_seconds": cfg.budget_seconds,
        "trials": cfg.trials, "reference_passes": cfg.reference_passes, "reference_seconds": ref_s,
        "reference_rel_mse": noise,
        "variants": [{"label": r.variant.label, "guiding": r.variant.guiding, "sampling": r.variant.sampling,
                      "edge_sort": r.variant.edge_sort, "fixed_passes": r.variant.passes, "rel_mse": r.rel_mse,
                      "rel_mse_trials": r.rel_mse_trials, "seconds": r.seconds, "passes": r.passes,
                      "build_seconds": r.build_seconds, "pass_seconds": r.pass_seconds, "guides": r.guides}
                     for r in result.rows]})
    return result


#: The paper's Table 2 (Yan et al. 2022; 32-core Threadripper Pro 3975WX + RTX Titan), for reference:
#: (scene, figure, target images, parameters, batch size, iterations, guiding memory, guiding s,
#: render s, post-processing s) per iteration.
PAPER_TABLE2 = (
    ("Dodoco", "Fig. 1", 70, "450,000", 2, 3000, "4 MB", 1.34, 2.59, 0.310),
    ("Jumpy Dumpty", "Fig. 9", 140, "60,000", 2, 520, "2 MB", 0.61, 1.11, 0.016),
    ("Klee", "Fig. 9", 40, "60,000", 1, 200, "2 MB", 0.33, 0.82, 0.016),
    ("Kirby", "Fig. 10", 35, "15,000", 1, 400, "80 KB", 0.91, 3.67, 0.017),
    ("Bunny in glass", "Fig. 10", 50, "30,000", 2, 2000, "128 KB", 1.79, 17.55, 0.022),
    ("Bunny shadow 2", "Fig. 10", 70, "30,000", 2, 600, "2 MB", 0.47, 0.72, 0.012),
    ("Duck", "Fig. 11", 35, "3,205,728", 1, 400, "2 MB", 0.34, 0.94, 0.092),
    ("Mora", "Fig. 11", 70, "150,001", 1, 1600, "4 MB", 0.43, 1.01, 0.109),
    ("Glass Dodoco", "Fig. 11", 140, "60,000", 1, 700, "400 KB", 0.94, 5.76, 0.093),
)


def table2(experiments: list, out: Path) -> Path:
    """The paper's Table 2 for our runs: per run of each experiment (all its optimize.variants),
    the configuration (target images, image size, samples, parameters = 3 × vertices, batch
    size, iterations) and the measured per-iteration time split (guiding, rendering,
    post-processing) and guide memory, from the runs' logs; the paper's own rows follow,
    labelled as such. Written as markdown to ``out``."""
    from . import evaluate as ev
    from .optimize import variant_experiments
    rows = ["| experiment | run | target images | image | spp (int/prim/bdry) | # param. | batch | # iter. | "
            "guide memory | guiding s/it | render s/it | post s/it |",
            "|---|---|---:|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for exp in experiments:
        if exp.optimize is None:
            raise PsdrError(f"{exp.file}: optimize: missing (table2 reports `psdr optimize` runs)")
        for label, run in variant_experiments(exp):
            if not (run.run_dir / "log.csv").exists():
                raise PsdrError(f"table2: run {run.run_dir} does not exist yet (run `psdr optimize {exp.file}` first)")
            s, e = ev.run_summary(run.run_dir), run.estimator
            memory = f"{s['guide_bytes'] / 1024:.0f} KiB" if s["guide_bytes"] else "—"
            rows.append(f"| {exp.name} | {label or '—'} | {s['views'] or len(exp.scene.cameras)} | "
                        f"{exp.scene.width}×{exp.scene.height} | {e.spp}/{e.primary_spp}/{e.boundary_spp} | "
                        f"{3 * s['vertices']:,} | {exp.optimize.batch_size} | {s['iterations']} | {memory} | "
                        f"{s['seconds_guiding']:.3f} s | {s['seconds_rendering']:.3f} s | {s['seconds_post']:.3f} s |")
    paper = ["| scene | figure | target images | # param. | batch | # iter. | guide memory | guiding s/it | "
             "render s/it | post s/it |", "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    paper += [f"| {r[0]} | {r[1]} | {r[2]} | {r[3]} | {r[4]} | {r[5]} | {r[6]} | {r[7]:.2f} s | {r[8]:.2f} s | "
              f"{r[9]:.3f} s |" for r in PAPER_TABLE2]
    text = ("## Our runs (measured on this machine)\n\n" + "\n".join(rows) +
            "\n\nGuiding: building the guides (amortised: rebuilt every `guide_every` iterations); render: the "
            "differentiable rendering of the mini-batch and its backward pass; post: the large-steps update, "
            "edge extraction and scene update.\n\n"
            "## The paper's Table 2 (for reference; their hardware: 32-core CPU and an RTX Titan GPU)\n\n"
            + "\n".join(paper) + "\n")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with io.atomic_path(out) as tmp:
        Path(tmp).write_text(text)
    return out
