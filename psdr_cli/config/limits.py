"""Resource limits: values are used in float32, and one huge number must not make a command run for
hours or exhaust memory (docs/config.md, "Limits")."""
from __future__ import annotations

#: Largest finite float32; every number must fit (Mitsuba and Dr.Jit compute in float32).
FLOAT32_MAX = 3.4028234663852886e38

#: Coordinates, sizes and scales: |x| ≤ this (squared distances must stay finite in float32).
MAX_COORD = 1e6

#: Radiances and emitter scales: ≤ this (a pixel sums spp of them in float32).
MAX_RADIANCE = 1e9

#: Samples per pixel of one image or term.
MAX_SPP = 1 << 20

#: Paths of one image (width · height · spp), about an hour of rendering on two CPU cores.
MAX_PATHS = 1 << 32

#: Film width and height.
MAX_FILM = 8192

#: Path length (scene.max_depth).
MAX_DEPTH = 64

#: Cells of a guide grid (nx · ny · nz) and samples spent building it.
MAX_GRID_CELLS = 1 << 22
MAX_GRID_SAMPLES = 1 << 28

#: Vertices of a remeshed shape (remesh.initial, remesh.vertices).
MAX_VERTICES = 500_000

#: Passes of one estimate (estimator.passes, compare.reference_passes).
MAX_PASSES = 1 << 16

#: Texels of one texture or environment-map file (16384 × 8192), checked before it is decoded.
MAX_TEXELS = 1 << 27

#: Iterations of one optimisation (optimize.iterations, --iterations).
MAX_ITERATIONS = 1_000_000

#: Points sampled per surface by ``psdr evaluate`` (evaluate.samples, --samples).
MIN_EVAL_SAMPLES, MAX_EVAL_SAMPLES = 100, 10_000_000

#: Largest |offset| of ``principal_point`` (film widths / heights): the principal point within
#: half a film beyond the film's edge.
MAX_PRINCIPAL_OFFSET = 1.0


def check_paths(spp: int, width: int, height: int, fail) -> int:
    """``spp`` if one image of ``width × height`` pixels at ``spp`` samples per pixel stays within
    :data:`MAX_SPP` and :data:`MAX_PATHS`; else ``fail(message)`` is raised."""
    if spp > MAX_SPP:
        raise fail(f"{spp} samples per pixel exceed the limit of {MAX_SPP} (a resource limit)")
    if spp * width * height > MAX_PATHS:
        raise fail(f"{spp} samples per pixel × {width}×{height} pixels = {spp * width * height:.3g} paths per image "
                   f"exceed the limit of {MAX_PATHS:.3g} (hours of rendering; a resource limit)")
    return spp
