"""Python API behind the CLI: each function runs one subcommand and returns what it wrote."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

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
