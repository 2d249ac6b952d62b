"""PNG plots (matplotlib, headless), each written atomically.

matplotlib is imported when the first plot is drawn (:func:`pyplot`): importing it takes about a
second (with pyparsing, fonttools and PIL), longer than most commands need before their first
output, and ``psdr --help`` or a rejected input draws nothing."""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from .fileio import atomic_path


@lru_cache(maxsize=None)
def pyplot():
    """matplotlib.pyplot on the headless Agg backend, imported and set up on first use."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def save(fig, path):
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    pyplot().close(fig)


def target_along_u1(path, curves: dict, title: str = ""):
    """Fig. 5 of the paper: per edge order, x^B(u1) (three coordinates, top) and the mean target
    over u2 along u1 (bottom). ``curves``: {label: (u1, xB (N,3), target (N,), breaks)}."""
    plt = pyplot()
    labels = list(curves)
    fig, axes = plt.subplots(2, len(labels), figsize=(5.5 * len(labels), 5.5), squeeze=False, sharex=True)
    for col, label in enumerate(labels):
        u1, xB, target, breaks = curves[label]
        ax = axes[0, col]
        for i, name in enumerate("xyz"):
            ax.plot(u1, xB[:, i], lw=0.7, label=name)
        ax.set_title(f"{label}: x^B(u1) — {len(breaks) - 1} continuous pieces")
        ax.legend(loc="upper right", fontsize=7)
        ax = axes[1, col]
        ax.plot(u1, target, lw=0.7, color="k")
        ax.set_yscale("symlog", linthresh=max(float(np.percentile(target[target > 0], 5)) if (target > 0).any() else 1e-6, 1e-12))
        ax.set_xlabel("u1")
        ax.set_ylabel("mean F̃ over u2")
    if title:
        fig.suptitle(title)
    save(fig, path)


def leaf_slice(path, lo, hi, density, u3: float = 0.5, u1_range=(0.0, 1.0), title: str = ""):
    """Leaves of a guide cut by the plane u2.y = ``u3``, drawn in (u1, u2.x), coloured by log
    density, for u1 in ``u1_range``."""
    plt = pyplot()
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Rectangle
    sel = (lo[:, 2] <= u3) & (hi[:, 2] > u3) & (hi[:, 0] > u1_range[0]) & (lo[:, 0] < u1_range[1])
    fig, ax = plt.subplots(figsize=(9, 4))
    rects = [Rectangle((a[0], a[1]), b[0] - a[0], b[1] - a[1]) for a, b in zip(lo[sel], hi[sel])]
    d = np.log10(np.maximum(density[sel], 1e-6))
    pc = PatchCollection(rects, cmap="viridis", edgecolor="w", linewidth=0.2)
    pc.set_array(d)
    ax.add_collection(pc)
    ax.set_xlim(*u1_range)
    ax.set_ylim(0, 1)
    ax.set_xlabel("u1")
    ax.set_ylabel("u2.x")
    fig.colorbar(pc, ax=ax, label="log10 guide density")
    ax.set_title(title or f"leaves at u2.y = {u3}")
    save(fig, path)


def lines(path, series: dict, xlabel: str, ylabel: str, title: str = "", logy: bool = False):
    """Simple line plot: ``series`` = {label: (x, y)}."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    for label, (x, y) in series.items():
        ax.plot(x, y, label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if logy:
        ax.set_yscale("log")
    if title:
        ax.set_title(title)
    if len(series) > 1:
        ax.legend()
    save(fig, path)


def chamfer(path, iterations, values, seconds, timed_values, floor: float):
    """Chamfer distance against iteration (left) and optimisation time (right), log scale, with
    the sampling noise floor."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for ax, x, y, label in ((axes[0], iterations, values, "iteration"), (axes[1], seconds, timed_values, "seconds")):
        ax.plot(x, y, "o-", ms=3)
        ax.axhline(floor, color="gray", ls="--", lw=0.8, label="sampling noise floor")
        ax.set_yscale("log")
        ax.set_xlabel(label)
        ax.set_ylabel("Chamfer-L1 (reference bbox = 1)")
        ax.legend(fontsize=7)
    save(fig, path)


def gradient_grid(path, reference, images, title: str, columns: int = 6):
    """Reference and variants' gradient images (sum over RGB) with a shared diverging scale and
    each variant's relMSE under its label. ``images``: [(label, (H, W, 3), relMSE)]."""
    plt = pyplot()
    n = len(images) + 1
    rows = (n + columns - 1) // columns
    fig, axes = plt.subplots(rows, columns, figsize=(2.2 * columns, 2.4 * rows), squeeze=False)
    scale = float(np.percentile(np.abs(reference.sum(-1)), 99)) or 1.0
    for ax in axes.ravel():
        ax.axis("off")
    panels = [("reference", reference, None)] + list(images)
    for ax, (label, img, err) in zip(axes.ravel(), panels):
        ax.imshow(img.sum(-1), cmap="RdBu_r", vmin=-scale, vmax=scale)
        ax.set_title(label + (f"\nrelMSE {err:.3g}" if err is not None else ""), fontsize=7)
    fig.suptitle(title, fontsize=9)
    save(fig, path)


def chamfer_runs(path, runs: dict, floor: float, title: str = ""):
    """Chamfer distance of several runs against iteration (left) and optimisation time (right),
    log scale; ``runs`` = {label: (iterations, seconds, values)} (seconds may hold None)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    colours = plt.cm.tab10.colors if len(runs) <= 10 else plt.cm.tab20.colors
    for k, (label, (its, secs, vals)) in enumerate(runs.items()):
        style = dict(color=colours[k % len(colours)], ms=3, label=label)
        axes[0].plot(its, vals, "o-", **style)
        timed = [(s, v) for s, v in zip(secs, vals) if s is not None]
        axes[1].plot([s for s, _ in timed], [v for _, v in timed], "o-", **style)
    for ax, label in zip(axes, ("iteration", "optimisation seconds")):
        ax.axhline(floor, color="gray", ls="--", lw=0.8, label="sampling noise floor")
        ax.set_yscale("log")
        ax.set_xlabel(label)
        ax.set_ylabel("Chamfer-L1 (reference bbox = 1)")
        ax.legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=9)
    save(fig, path)


def image_grid(path, panels: list, title: str = "", columns: int = 4):
    """sRGB pictures in a grid with a caption under each; ``panels`` = [(caption, (H, W, 3) in [0, 1])]."""
    plt = pyplot()
    rows = (len(panels) + columns - 1) // columns
    fig, axes = plt.subplots(rows, columns, figsize=(2.6 * columns, 2.9 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (caption, img) in zip(axes.ravel(), panels):
        ax.imshow(np.clip(img, 0, 1))
        ax.set_title(caption, fontsize=7, y=-0.2)
    if title:
        fig.suptitle(title, fontsize=9)
    save(fig, path)
