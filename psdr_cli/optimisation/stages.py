"""The schedule of an optimisation: its remesh stages and what changes at each (λ, the film's
downsampling, the targets at that resolution, whether the film is guided)."""
from __future__ import annotations

from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from ..rendering.estimate import uses_guides
from ..support.jitarray import jit_array


def stage_at(cfg, iteration: int) -> int:
    """Remesh stage of the shape that ``iteration`` optimises: the number of entries a > 0 of
    ``remesh.at`` with a ≤ iteration (the remesh at a happens at the start of iteration a; stage 0
    is the initial shape)."""
    return sum(1 for a in cfg.remesh.at if 0 < a <= iteration)


def stage_value(values: tuple, stage: int):
    """The value of a per-stage key (``lambda``, ``downsample``) at ``stage``; a single value holds
    for every stage."""
    return values[min(stage, len(values) - 1)]


def downsample(image: np.ndarray, k: int) -> np.ndarray:
    """Mean of every k × k block of pixels of an (H, W, C) image. With the box pixel filter every
    render uses, a pixel of the W/k × H/k film integrates exactly the area of its k² pixels at
    W × H, so this is the target a render at the lower resolution would estimate."""
    if k == 1:
        return image
    H, W, C = image.shape
    return image.reshape(H // k, k, W // k, k, C).mean(axis=(1, 3))


def stage_images(targets, k: int):
    """The targets at downsampling factor ``k``: (H/k, W/k, 3) arrays and flat ``mi.Float`` copies."""
    images = [downsample(t, k) for t in targets]
    return images, [jit_array(mi.Float, np.ravel(t)) for t in images]


@dataclass
class Stage:
    """What a remesh stage renders against: its downsampling factor, the targets at that factor
    ((H/k, W/k, 3) arrays and flat ``mi.Float`` copies), whether its film is guided, its pixels,
    the targets' masks at that factor (flat W·H ``mi.Float``, or None without masks) and the L1
    weights (flat W·H·3, or None)."""
    factor: int
    images: list
    arrays: list
    guided: bool
    pixels: int
    masks: list | None = None
    weights: list | None = None


def stage_of(problem, targets, settings, terms, previous: Stage | None = None,
             masks=None) -> Stage:
    """The stage ``problem`` renders (``previous`` again while its downsampling is unchanged);
    ``masks``: the targets' :class:`~psdr_cli.target_sources.source.TargetMasks`, or None."""
    if previous is not None and previous.factor == problem.factor:
        return previous
    images, arrays = stage_images(targets, problem.factor)
    pixels = pixel_count(problem)
    stage = Stage(problem.factor, images, arrays, uses_guides(settings, terms), pixels)
    if masks is not None:
        stage.masks = stage_images([m[..., None] for m in masks.masks], problem.factor)[1]
    if masks is not None and masks.weights is not None:
        stage.weights = [jit_array(mi.Float, np.ravel(np.repeat(block_min(w, problem.factor)[..., None], 3, -1)))
                         for w in masks.weights]
    return stage


def block_min(image: np.ndarray, k: int) -> np.ndarray:
    """The least value of every k × k block of an (H, W) array: a weight of 0 anywhere in a block
    (a pixel the loss must not see) stays 0 at the coarser stage."""
    H, W = image.shape
    return image.reshape(H // k, k, W // k, k).min(axis=(1, 3))


def pixel_count(problem) -> int:
    """Pixels of the film the current stage renders (what ``guiding: auto`` decides by)."""
    width, height = problem.scene.resolution
    return width * height
