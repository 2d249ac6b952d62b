"""Shape error (``psdr evaluate``): symmetric Chamfer and Hausdorff distances to a reference
(:mod:`psdr_cli.scoring.mesh_distance`), held-out scores and relighting of runs on camera
datasets. Reads meshes and run folders; writes the evaluation's report, JSON, plots and mesh
copies."""
from __future__ import annotations

import json
import shutil
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import mitsuba as mi
import numpy as np

from ..config.experiment_file import read_file
from ..config.limits import MAX_COORD, MAX_EVAL_SAMPLES, MIN_EVAL_SAMPLES
from ..config.options import option_count
from ..errors import PsdrError
from ..scoring.held_out import score_mesh
from ..scoring.mesh_distance import distance, noise_floor
from ..scoring.held_out_geometry import check_units
from ..experiment.dataset_frame import dataset_frames
from ..experiment.load import load_experiment
from ..run_folder.checkpoints import run_checkpoints
from ..run_folder.layout import RunFiles
from ..run_folder.log import run_seconds, run_summary
from ..run_folder.variant_folders import existing_runs, variant_experiments
from ..scene.build import look_at, mitsuba_mesh
from ..scene.meshes import face_areas, read_mesh_file
from ..support import backend, fileio, plots
from .relight import check_latlong, relight_mesh


def load(path: Path):
    """(V, F) of a PLY/OBJ mesh with one-line errors for missing, unreadable or empty files, and
    for meshes no distance can be measured on (:func:`mesh_problem`)."""
    path = Path(path)
    if not path.exists():
        raise PsdrError(f"{path}: file not found")
    try:
        V, F = read_mesh_file(path)
    except Exception as exc:  # noqa: BLE001 - any parser failure
        raise PsdrError(f"{path}: cannot read mesh ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    problem = mesh_problem(V, F)
    if problem:
        raise PsdrError(f"{path}: {problem}")
    return V, F


def mesh_problem(V, F) -> str | None:
    """Why points cannot be sampled on (V, F), or None: an empty mesh, face indices outside the
    vertex list, vertices that are not finite or beyond ±MAX_COORD (a far vertex squeezes the rest
    of the normalised mesh into one point, and the nearest-point search then takes hours), or no
    surface area."""
    V, F = np.asarray(V, float), np.asarray(F, np.int64)
    if len(V) == 0 or len(F) == 0:
        return f"mesh is empty ({len(V)} vertices, {len(F)} triangles)"
    if F.min() < 0 or F.max() >= len(V):
        return f"mesh has face indices outside 0..{len(V) - 1} (e.g. {int(F[(F < 0) | (F >= len(V))][0])})"
    bad = ~np.isfinite(V).all(axis=1)
    if bad.any():
        return f"mesh has {int(bad.sum())} vertices with NaN or infinite coordinates"
    far = (np.abs(V) > MAX_COORD).any(axis=1)
    if far.any():
        return f"mesh has {int(far.sum())} vertices with coordinates beyond ±{MAX_COORD:g} (e.g. {V[far][0].tolist()})"
    if not face_areas(V, F).sum() > 0:
        return f"mesh has zero surface area (all {len(F)} triangles are degenerate)"
    return None


def mesh_view(V, F, reference_V, size: int = 160, spp: int = 64, direction=(0.55, -1.0, 0.45)) -> np.ndarray:
    """A neutral picture of a mesh for side-by-side comparisons (H, W, 3 in [0, 1] sRGB): grey
    two-sided diffuse under a constant sky and a directional key light, framed on the *reference's*
    bounding sphere so that all meshes of one comparison share the camera."""
    lo, hi = reference_V.min(0), reference_V.max(0)
    centre, radius = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 3},
        "sensor": {"type": "perspective", "fov": 32, "to_world": look_at(centre + d * radius * 3.6, centre, (0, 0, 1)),
                   "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.35}},
        "key": {"type": "directional", "direction": [-0.4, 0.8, -0.9], "irradiance": {"type": "rgb", "value": 2.2}},
        "mesh": mitsuba_mesh("mesh", V, F, {"type": "twosided", "bsdf": {
            "type": "diffuse", "reflectance": {"type": "rgb", "value": 0.6}}}),
    })
    return fileio.srgb(np.asarray(mi.render(scene, spp=spp), np.float64)[..., :3])


# --------------------------------------------------------------------------------------------
# psdr evaluate
# --------------------------------------------------------------------------------------------
@dataclass
class EvaluateResult:
    reference: Path
    rows: list = field(default_factory=list)       # {mesh, iteration, seconds, chamfer_l1, chamfer_l2, hausdorff}
    noise_floor: dict = field(default_factory=dict)
    plots: list = field(default_factory=list)
    report: Path | None = None


@dataclass
class EvaluateInputs:
    """What ``psdr evaluate PATH…`` compares (:func:`evaluate_inputs`): the reference mesh, the
    meshes or run folders, the surface samples and their seed, and the side-by-side report of
    several runs (its folder, None: no report; the runs' labels and the report's title)."""
    reference: Path
    paths: list
    samples: int = 100_000
    seed: int = 0
    report: Path | None = None
    labels: list | None = None
    title: str = ""


def evaluate_meshes(inputs: EvaluateInputs, json_out: Path | None = None, progress=None) -> EvaluateResult:
    """Chamfer/Hausdorff distances of meshes (or of every checkpoint of run folders) to
    ``inputs.reference``; a run folder also gets ``chamfer.png`` (distance against iteration and
    time)."""
    reference, paths, samples, seed = inputs.reference, inputs.paths, inputs.samples, inputs.seed
    report, labels, title = inputs.report, inputs.labels, inputs.title
    option_count("--samples", samples, MIN_EVAL_SAMPLES, MAX_EVAL_SAMPLES)
    if json_out:  # outputs that cannot be written are refused before the work
        fileio.check_output_file(json_out, "--json")
    if report:
        fileio.writable_folder(report)
    ref = load(reference)
    jobs = []  # (label, path, iteration, seconds, run folder)
    for p in map(Path, paths):
        if p.is_dir():
            secs = run_seconds(p)
            jobs += [(str(path), path, i, secs.get(i, 0.0 if i == 0 else None), p) for i, path in run_checkpoints(p)]
        else:
            jobs.append((str(p), p, None, None, None))
    if not jobs:
        raise PsdrError("evaluate: no meshes given (expected mesh files or `psdr optimize` run folders)")
    for _, path, _, _, _ in jobs:  # every mesh checked before any work (and any progress line)
        load(path)
    result = EvaluateResult(Path(reference), noise_floor=asdict(noise_floor(ref, samples, seed)))
    if progress:
        progress.start(len(jobs))
    for label, path, iteration, seconds, run in jobs:
        d = distance(load(path), ref, samples, seed)
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
        fileio.write_json(Path(json_out), {"reference": str(reference), "samples": samples, "seed": seed,
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
    backend.select_variant("auto")  # the mesh pictures render with Mitsuba
    folder.mkdir(parents=True, exist_ok=True)
    series, panels, table, summary = {}, [("reference", mesh_view(*ref, ref[0]))], [], []
    for run, label in zip(runs, labels):
        rows = [r for r in result.rows if r["run"] == str(run)]
        series[label] = ([r["iteration"] for r in rows], [r["seconds"] for r in rows], [r["chamfer_l1"] for r in rows])
        last, s = rows[-1], run_summary(run)
        panels.append((f"{label}\nChamfer-L1 {last['chamfer_l1']:.4f}", mesh_view(*load(last["mesh"]), ref[0])))
        with fileio.atomic_path(folder / f"{label}.ply") as tmp:
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
    with fileio.atomic_path(folder / "evaluate.md") as tmp:
        Path(tmp).write_text("\n".join(header + table) + f"\n\nSampling noise floor (Chamfer-L1): {floor:.5f}\n")
    fileio.write_json(folder / "evaluate.json", {"noise_floor": result.noise_floor, "runs": summary})
    with fileio.atomic_path(folder / "reference.ply") as tmp:
        shutil.copyfile(result.reference, tmp)
    return folder


# --------------------------------------------------------------------------------------------
# psdr evaluate on a camera dataset: held-out views
# --------------------------------------------------------------------------------------------
@dataclass
class HeldOutReport:
    """Scores of a dataset run's initial and final meshes on the held-out views
    (:mod:`psdr_cli.scoring.held_out`), one row per mesh, with Chamfer/Hausdorff when a reference is given."""
    experiment: Path
    folders: list = field(default_factory=list)
    rows: list = field(default_factory=list)


def dataset_experiment(paths):
    """The experiment of ``paths`` when they are one experiment file that reconstructs from a
    camera dataset (``optimize.target.dataset``), else None."""
    configs = [str(p) for p in paths or [] if str(p).endswith((".yaml", ".yml"))]
    if len(configs) != 1 or len(paths) != 1:
        return None
    exp = read_file(configs[0])
    return load_experiment(configs[0]) if exp.optimize and exp.optimize.target_dataset else None


def held_out_row(exp, mesh: Path, iteration: int, out: Path, reference, samples: int, *, align: str = "auto",
                 max_depth: int | None = None) -> dict:
    """One mesh of a run scored on the held-out views (means over the views), and against
    ``reference`` (V, F) when given; the held-out cameras fitted first with ``align`` ``on``, or
    ``auto`` when the run refined its cameras (the initial mesh is scored as given); rendered
    with paths of ``max_depth`` segments (default: the run's ``scene.max_depth``)."""
    exp = with_depth(exp, max_depth)
    values = run_values(exp.run_dir) if iteration > 0 else {}
    align = iteration > 0 and (align == "on" or (align == "auto" and "cameras" in values))
    scores = score_mesh(exp, mesh, out=out, values=values, align=align, reference=reference)
    keys = ("psnr", "psnr_mask", "ssim", "ssim_mask", "iou")
    row = {"mesh": str(mesh), "iteration": iteration, "views": len(scores.views), "max_depth": exp.scene.max_depth,
           "poses": "aligned" if align else "as given", **{k: scores.mean(k, aligned=align) for k in keys}}
    if align:
        row["as_given"] = {k: scores.mean(k) for k in keys}
        row["alignment_deg"] = [float(r) for r, _ in scores.alignment]
    if any(s != 1.0 for s in scores.focal_scales):
        row["focal_scales"] = [float(s) for s in scores.focal_scales]
    if reference is not None:
        row.update(asdict(distance(load(mesh), reference, samples)))
        row.update({k: scores.geometry_mean(k) for k in ("depth_error", "normal_deg", "normal_cosine")})
    return row


def with_depth(exp, max_depth: int | None):
    """``exp`` rendering paths of ``max_depth`` segments (``exp`` itself when None)."""
    if max_depth is None:
        return exp
    return replace(exp, scene=replace(exp.scene, max_depth=max_depth))


def run_values(folder: Path) -> dict:
    """The unknowns a finished run recovered (``optimize.json`` ``values``), or {} without them."""
    try:
        return json.loads(RunFiles(folder).summary.read_text()).get("values", {})
    except (OSError, ValueError, AttributeError):
        return {}


def evaluate_held_out(exp, reference: Path | None = None, samples: int | None = None, json_out: Path | None = None,
                      progress=None, align: str = "auto", max_depth: int | None = None) -> HeldOutReport:
    """``psdr evaluate`` of a dataset experiment: each run's initial and last checkpoint
    rendered from the held-out cameras (paths of ``max_depth`` segments, default each run's
    ``scene.max_depth``) and scored (PSNR, SSIM, mask IoU), with a
    target | render | error strip per view in ``<run>/held_out/``, ``held_out.json`` and
    ``held_out.md`` there; Chamfer and Hausdorff too with ``reference`` (or ``evaluate.reference``)."""
    reference = reference or (exp.evaluate.reference if exp.evaluate else None)
    samples = samples or (exp.evaluate.samples if exp.evaluate else 100_000)
    if json_out:
        fileio.check_output_file(json_out, "--json")
    ref = load(reference) if reference is not None else None
    if ref is not None:  # in the dataset's units: against the runs' initial meshes
        for _, run in variant_experiments(exp):
            if RunFiles(run.run_dir).checkpoints.is_dir():
                check_units(ref, load(run_checkpoints(run.run_dir)[0][1]), reference)
    result = HeldOutReport(exp.file)
    runs = variant_experiments(exp)
    dataset_frames(exp.optimize.target_dataset, "test")  # no held-out views: one line before anything is written
    jobs = []
    for _, run in runs:
        if not RunFiles(run.run_dir).checkpoints.is_dir():
            raise PsdrError(f"evaluate: {run.run_dir} holds no run yet (run `psdr optimize {exp.file}` first)")
        found = run_checkpoints(run.run_dir)
        jobs += [(run, i, path) for i, path in (found[:1] + found[1:][-1:])]  # the initial and the last mesh
    if progress:
        progress.start(len(jobs))
    for run, iteration, path in jobs:
        folder = fileio.writable_folder(run.run_dir / "held_out")
        result.rows.append(held_out_row(run, path, iteration, folder, ref, samples, align=align, max_depth=max_depth))
        if folder not in result.folders:
            result.folders.append(folder)
        if progress:
            progress.advance(1)
    for folder in result.folders:
        rows = [r for r in result.rows if Path(r["mesh"]).parent in (folder.parent, folder.parent / "checkpoints")]
        fileio.write_json(folder / "held_out.json", {"experiment": str(exp.file), "meshes": rows})
        with fileio.atomic_path(folder / "held_out.md") as tmp:
            Path(tmp).write_text(held_out_table(rows))
    if json_out:
        fileio.write_json(Path(json_out), {"experiment": str(exp.file), "meshes": result.rows})
    return result


@dataclass
class Relight:
    """``psdr evaluate --relight DATASET --envmap MAP [--envmap-scale s]``."""
    dataset: Path
    envmap: Path
    scale: float = 1.0


def evaluate_relit(exp, relight: Relight, json_out: Path | None = None, progress=None) -> HeldOutReport:
    """Each run's last mesh with what it recovered, relit by ``relight.envmap`` from the cameras of
    ``relight.dataset`` and scored against its photographs (:mod:`psdr_cli.commands.relight`): means over
    the views in ``<run>/relight/relight.json`` and ``relight.md``, a strip per view there
    (``exp`` None: the paths given were not one dataset experiment, refused in one line)."""
    if exp is None:
        raise PsdrError("--relight: expected one experiment file that reconstructs from a camera dataset")
    if json_out:
        fileio.check_output_file(json_out, "--json")
    check_latlong(relight.envmap)
    result = HeldOutReport(exp.file)
    runs = []
    for _, run in variant_experiments(exp):
        if not RunFiles(run.run_dir).checkpoints.is_dir():
            raise PsdrError(f"evaluate: {run.run_dir} holds no run yet (run `psdr optimize {exp.file}` first)")
        runs.append((run, run_checkpoints(run.run_dir)[-1]))
    if progress:
        progress.start(len(runs))
    for run, (iteration, mesh) in runs:
        folder = fileio.writable_folder(run.run_dir / "relight")
        scores = relight_mesh(run, mesh, relight.dataset, relight.envmap, scale=relight.scale,
                              values=run_values(run.run_dir), out=folder)
        row = {"mesh": str(mesh), "iteration": iteration, "views": len(scores.views), "dataset": str(relight.dataset),
               "envmap": str(relight.envmap), "envmap_scale": relight.scale,
               **{k: scores.mean(k) for k in ("psnr_h", "psnr_l", "ssim", "iou")},
               "per_view": [asdict(v) for v in scores.views]}
        result.rows.append(row)
        result.folders.append(folder)
        fileio.write_json(folder / "relight.json", {"experiment": str(exp.file), **row})
        with fileio.atomic_path(folder / "relight.md") as tmp:
            Path(tmp).write_text(relight_table([row]))
        if progress:
            progress.advance(1)
    if json_out:
        fileio.write_json(Path(json_out), {"experiment": str(exp.file), "relight": result.rows})
    return result


def relight_table(rows: list) -> str:
    """A markdown table of relit scores (:func:`evaluate_relit`)."""
    lines = ["| mesh | iteration | views | PSNR-H | PSNR-L | SSIM | mask IoU |", "|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {Path(r['mesh']).name} | {r['iteration']} | {r['views']} | {r['psnr_h']:.2f} | "
                     f"{r['psnr_l']:.2f} | {r['ssim']:.4f} | {r['iou']:.4f} |")
    return "\n".join(lines + ["", f"Relit by {rows[0]['envmap']} (scale {rows[0]['envmap_scale']:g}) from the cameras "
                              f"of {rows[0]['dataset']}; each render scaled per channel by least squares in the mask "
                              f"before scoring (light × albedo is ambiguous)."]) + "\n"


def held_out_table(rows: list) -> str:
    """A markdown table of held-out scores (:func:`evaluate_held_out`)."""
    fmt = lambda v, f: "—" if v is None else format(v, f)  # noqa: E731
    lines = ["| mesh | iteration | views | max_depth | poses | PSNR | PSNR in mask | SSIM | SSIM in mask | mask IoU | "
             "PSNR, poses as given | Chamfer-L1 | depth error | normal angle (°) |",
             "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        given = r.get("as_given", r)
        lines.append(f"| {Path(r['mesh']).name} | {r['iteration']} | {r['views']} | {r.get('max_depth', '—')} | "
                     f"{r.get('poses', 'as given')} | "
                     f"{fmt(r['psnr'], '.2f')} | {fmt(r['psnr_mask'], '.2f')} | {fmt(r['ssim'], '.4f')} | "
                     f"{fmt(r['ssim_mask'], '.4f')} | {fmt(r['iou'], '.4f')} | {fmt(given['psnr'], '.2f')} | "
                     f"{fmt(r.get('chamfer_l1'), '.5f')} | {fmt(r.get('depth_error'), '.2e')} | "
                     f"{fmt(r.get('normal_deg'), '.2f')} |")
    notes = ("", "Rows with poses 'aligned': each held-out camera was fitted to its photograph with the recovered "
             "scene fixed before scoring (the run refined its training cameras); the column 'poses as given' "
             "scores the cameras as the dataset gives them.")
    focal = ("", "Held-out cameras of a camera model whose focal length the run refined were scored at the "
             "refined focal length (scales in held_out.json, 'focal_scales').")
    lines += list(notes) if any(r.get("poses") == "aligned" for r in rows) else []
    return "\n".join(lines + (list(focal) if any("focal_scales" in r for r in rows) else [])) + "\n"


def evaluate_inputs(paths, reference: Path | None = None, samples: int | None = None,
                    report: Path | None = None) -> EvaluateInputs:
    """What ``psdr evaluate PATH…`` compares (:class:`EvaluateInputs`). An experiment file among ``paths`` names its runs (all its
    variants, reported side by side) and its ``evaluate:`` defaults; the reference is, in this
    order, ``reference``, ``evaluate.reference``, or the first run's ``reference.ply``."""
    paths = [str(p) for p in paths or []]
    option_count("--samples", samples, MIN_EVAL_SAMPLES, MAX_EVAL_SAMPLES)  # 0 is an error, not the default
    seed, labels, title = 0, None, ""
    configs = [p for p in paths if p.endswith((".yaml", ".yml"))]
    targets = [Path(p) for p in paths if not p.endswith((".yaml", ".yml"))]
    if len(configs) > 1:
        raise PsdrError("evaluate: give at most one experiment file")
    if configs:
        exp = read_file(configs[0])  # its runs and evaluate: section (the scene is not needed)
        if exp.evaluate:
            reference = reference or exp.evaluate.reference
            samples = samples or exp.evaluate.samples
            seed = exp.evaluate.seed
        if not targets:
            runs = variant_experiments(exp) if exp.optimize else [(None, exp)]
            targets = [e.run_dir for _, e in runs]
            if runs[0][0] is not None:
                labels, title = [label for label, _ in runs], exp.name
                report = report or exp.run_dir
                existing_runs(exp, "evaluate")
    if reference is None:
        runs = [t for t in targets if RunFiles(t).reference.exists()]
        if runs:
            reference = RunFiles(runs[0]).reference
    if reference is None:
        raise PsdrError("evaluate: no reference mesh (give --reference gt.ply, evaluate.reference in the "
                        "experiment, or a run folder with reference.ply)")
    if not targets:
        raise PsdrError("evaluate: nothing to evaluate (give meshes or `psdr optimize` run folders)")
    return EvaluateInputs(reference, targets, 100_000 if samples is None else samples, seed, report, labels, title)


# --------------------------------------------------------------------------------------------
# psdr table2
# --------------------------------------------------------------------------------------------
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
    out = fileio.check_output_file(out, "--out")
    rows = ["| experiment | run | target images | image | spp (int/prim/bdry) | # param. | batch | # iter. | "
            "guide memory | guiding s/it | render s/it | post s/it |",
            "|---|---|---:|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for exp in experiments:
        if exp.optimize is None:
            raise PsdrError(f"{exp.file}: optimize: missing (table2 reports `psdr optimize` runs)")
        existing_runs(exp, "table2")
        for label, run in variant_experiments(exp):
            s, e = run_summary(run.run_dir), run.estimator
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
    fileio.writable_folder(out.parent)
    with fileio.atomic_path(out) as tmp:
        Path(tmp).write_text(text)
    return out
