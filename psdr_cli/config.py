"""Experiment files: YAML parsed into typed objects, validated in one place.

Every problem is reported as one :class:`~psdr_cli.errors.ConfigError` line naming the file, the
key path and what was expected, e.g.
``bunny.yaml: scene.objects[1].bsdf.type: unknown 'difuse' (expected diffuse, roughconductor, ...)``.
Unknown keys are errors, so a typo never passes silently. The key reference is ``docs/config.md``.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import yaml

from .errors import ConfigError, PsdrError

REQUIRED = object()

# --------------------------------------------------------------------------------------------
# Vocabularies: every name a key or command-line option accepts is defined here, once.
# --------------------------------------------------------------------------------------------
#: Terms of dI/dθ = interior + primary + direct + indirect (in this order).
TERMS = ("interior", "primary", "direct", "indirect")
#: Boundary guides over the primary samples u.
GUIDINGS = ("auto", "none", "grid", "kdtree")
#: Direction techniques of the boundary terms (``mis``: both, balance heuristic).
SAMPLINGS = ("dir", "light", "mis")
PRIMARY_SAMPLINGS = ("length", "jump")  # primary-term edge density (estimators/primary.py)
#: Remeshers (``none``: keep the mesh; a scheduled remesh then uses ``isotropic``).
REMESH_METHODS = ("instant", "isotropic", "none")
#: Renderers of an optimisation's gradient images (``mitsuba``: Mitsuba's projective integrators).
ENGINES = ("psdr", "mitsuba")
#: Mitsuba's projective integrators (``estimator.mitsuba_integrator``).
MITSUBA_INTEGRATORS = ("direct_projective", "prb_projective")
#: Mitsuba variants (``auto``: CUDA when present, else LLVM).
VARIANTS = ("auto", "llvm_ad_rgb", "cuda_ad_rgb")

# --------------------------------------------------------------------------------------------
# Limits: values are used in float32, and one huge number must not make a command run for hours
# or exhaust memory (docs/config.md, "Limits").
# --------------------------------------------------------------------------------------------
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
#: First character of the Mitsuba ids psdr gives its own scene entries (cameras, emitters, the
#: integrator): no object name may start with it, so user names never meet psdr's.
INTERNAL_PREFIX = "@"
INTEGRATOR_ID = INTERNAL_PREFIX + "integrator"


def sensor_id(i: int) -> str:
    """Mitsuba id of camera ``i`` (``@sensor_000``)."""
    return f"{INTERNAL_PREFIX}sensor_{i:03d}"


def emitter_id(i: int) -> str:
    """Mitsuba id of emitter ``i`` (``@emitter_00``)."""
    return f"{INTERNAL_PREFIX}emitter_{i:02d}"


def name_problem(name: str) -> str | None:
    """Why ``name`` cannot name a scene object (a Mitsuba id beside psdr's own), or None."""
    if name.startswith(INTERNAL_PREFIX):
        return (f"'{name}' is reserved (names starting with '{INTERNAL_PREFIX}' are psdr's own ids for cameras, "
                f"emitters and the integrator); choose another name")
    if name == "type":
        return "'type' is reserved (Mitsuba's scene dictionary uses it); choose another name"
    if "." in name:
        return f"'{name}' contains '.', which separates Mitsuba parameter names (use '_')"
    return None


# --------------------------------------------------------------------------------------------
# Reading helpers: a Section is one YAML mapping with its key path; parsers check one value.
# --------------------------------------------------------------------------------------------
@dataclass
class Where:
    """Location of a value: the experiment file and the dotted key path inside it."""
    file: str
    path: str

    def fail(self, message: str) -> ConfigError:
        return ConfigError(self.file, self.path, message)

    def child(self, key) -> "Where":
        if isinstance(key, int):
            return Where(self.file, f"{self.path}[{key}]")
        return Where(self.file, f"{self.path}.{key}" if self.path else str(key))


Parser = Callable[[Any, Where], Any]


def _describe(value) -> str:
    if value is None:
        return "nothing"
    if isinstance(value, bool):
        return f"boolean {str(value).lower()}"
    if isinstance(value, int) and abs(value) > FLOAT32_MAX:
        return f"a {len(str(abs(value)))}-digit integer"
    if isinstance(value, (int, float)):
        return f"number {value}"
    if isinstance(value, str):
        return f"string '{value}'"
    if isinstance(value, list):
        if len(value) <= 8 and all(isinstance(v, (int, float, str, bool)) or v is None for v in value):
            return "[" + ", ".join(_describe(v) if isinstance(v, int) and abs(v) > FLOAT32_MAX else str(v)
                                   for v in value) + "]"
        return f"a list of {len(value)}"
    if isinstance(value, dict):
        return "a mapping"
    return type(value).__name__


class Section:
    """A YAML mapping being read; :meth:`done` rejects every key that was not read."""

    def __init__(self, data, where: Where):
        if not isinstance(data, dict):
            raise where.fail(f"expected a mapping of keys, got {_describe(data)}")
        self.data, self.where, self.used = data, where, set()

    def has(self, key: str) -> bool:
        return self.data.get(key) is not None

    def get(self, key: str, parse: Parser, default=REQUIRED):
        self.used.add(key)
        value = self.data.get(key)
        if value is None:
            if default is REQUIRED:
                raise self.where.child(key).fail("missing (required)")
            return default
        return parse(value, self.where.child(key))

    def done(self):
        unknown = [k for k in self.data if k not in self.used]
        if unknown:
            allowed = ", ".join(sorted(str(k) for k in self.used))
            raise self.where.child(unknown[0]).fail(f"unknown key (expected one of: {allowed})")


def integer(minimum: int | None = None, maximum: int | None = None) -> Parser:
    """An integer in [minimum, maximum]; a bound that is exceeded is named in the message."""
    def parse(value, where):
        if isinstance(value, float) and value.is_integer() and abs(value) < 2 ** 63:
            value = int(value)  # YAML reads 1e12 as a float
        if isinstance(value, bool) or not isinstance(value, int):
            raise where.fail(f"expected an integer, got {_describe(value)}")
        got = _describe(value) if abs(value) > FLOAT32_MAX else value  # not 400 digits
        if minimum is not None and value < minimum:
            raise where.fail(f"expected an integer >= {minimum}, got {got}")
        if maximum is not None and value > maximum:
            raise where.fail(f"expected an integer <= {maximum} (a resource limit), got {got}")
        return value
    return parse


def finite(value) -> bool:
    """``math.isfinite`` for YAML numbers: an integer too large for a float (400 digits) is not
    finite either (instead of an OverflowError)."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def finite32(value) -> bool:
    """Whether ``value`` is a number that is finite in float32 (the precision it is used in)."""
    return (isinstance(value, (int, float)) and not isinstance(value, bool) and finite(value)
            and abs(value) <= FLOAT32_MAX)


def number(minimum: float | None = None, positive: bool = False, maximum: float | None = None) -> Parser:
    def parse(value, where):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (
                isinstance(value, float) and not math.isfinite(value)):  # (a 400-digit integer: below)
            raise where.fail(f"expected a number, got {_describe(value)}")
        if not finite32(value):
            got = _describe(value) if isinstance(value, int) else value
            raise where.fail(f"expected a number representable in float32 (|x| <= 3.4e38), got {got}")
        if positive and value <= 0:
            raise where.fail(f"expected a number > 0, got {value}")
        if minimum is not None and value < minimum:
            raise where.fail(f"expected a number >= {minimum}, got {value}")
        if maximum is not None and value > maximum:
            raise where.fail(f"expected a number <= {maximum}, got {value}")
        return float(value)
    return parse


def boolean(value, where):
    if not isinstance(value, bool):
        raise where.fail(f"expected true or false, got {_describe(value)}")
    return value


def string(value, where):
    if not isinstance(value, str) or not value.strip():
        raise where.fail(f"expected a non-empty string, got {_describe(value)}")
    if "\0" in value:  # no file name (and no folder psdr names after it) can hold one
        raise where.fail("expected a string without NUL characters")
    return value


def choice(*options: str) -> Parser:
    def parse(value, where):
        if not isinstance(value, str):
            raise where.fail(f"expected one of {', '.join(options)}, got {_describe(value)}")
        if value not in options:
            raise where.fail(f"unknown '{value}' (expected {', '.join(options)})")
        return value
    return parse


def vector(n: int = 3, nonzero: bool = False, positive: bool = False, bound: float = MAX_COORD) -> Parser:
    """A list of ``n`` finite numbers with |x| ≤ ``bound``."""
    def parse(value, where):
        ok = isinstance(value, (list, tuple)) and len(value) == n and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
        if not ok:
            raise where.fail(f"expected a list of {n} numbers, got {_describe(value)}")
        if not all(finite(v) for v in value):
            raise where.fail(f"expected {n} finite numbers, got {_describe(list(value))}")
        if max(abs(v) for v in value) > bound:
            raise where.fail(f"expected {n} numbers within ±{bound:g}, got {_describe(list(value))}")
        out = tuple(float(v) for v in value)
        if nonzero and not any(out):
            raise where.fail("expected a non-zero vector")
        if positive and min(out) <= 0:
            raise where.fail(f"expected {n} numbers > 0, got {list(value)}")
        return out
    return parse


def color(value, where, maximum: float = MAX_RADIANCE):
    """A non-negative RGB value in [0, ``maximum``]: one number (grey) or [r, g, b]."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value] * 3
    rgb = vector(3, bound=FLOAT32_MAX)(value, where) if isinstance(value, (list, tuple)) else None
    if rgb is None:
        raise where.fail(f"expected a number or a list of 3 numbers, got {_describe(value)}")
    if min(rgb) < 0 or max(rgb) > maximum:
        raise where.fail(f"expected non-negative values <= {maximum:g}, got {_describe(list(value))}")
    return rgb


def reflectance(value, where):
    """An albedo: one number or [r, g, b] in [0, 1] (energy conservation)."""
    return color(value, where, maximum=1.0)


def scale3(value, where):
    """A positive scale: one number (uniform) or [sx, sy, sz]."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value] * 3
    return vector(3, positive=True)(value, where)


def list_of(parse_item: Parser, min_len: int = 0) -> Parser:
    def parse(value, where):
        if not isinstance(value, list):
            raise where.fail(f"expected a list, got {_describe(value)}")
        if len(value) < min_len:
            raise where.fail(f"expected at least {min_len} entr{'y' if min_len == 1 else 'ies'}")
        return [parse_item(v, where.child(i)) for i, v in enumerate(value)]
    return parse


def path_relative_to(base: Path) -> Parser:
    def parse(value, where):
        return (base / string(value, where)).resolve()
    return parse


def _unit(v):
    n = math.sqrt(sum(c * c for c in v))
    return tuple(c / n for c in v)


# --------------------------------------------------------------------------------------------
# Typed configuration objects
# --------------------------------------------------------------------------------------------
@dataclass
class CameraConfig:
    origin: tuple
    target: tuple
    up: tuple = (0.0, 0.0, 1.0)
    fov: float = 40.0  # horizontal, degrees
    #: Mitsuba's ``principal_point_offset_x/y``: the principal point sits at pixel
    #: (W·(½ − ox), H·(½ − oy)), so a positive offset moves it left / up (fractions of the film).
    principal_point: tuple = (0.0, 0.0)


@dataclass
class EmitterConfig:
    type: str  # area | envmap | sky | constant
    key: str   # key path in the file, for error messages
    radiance: tuple = (1.0, 1.0, 1.0)
    center: tuple = (0.0, 0.0, 0.0)
    normal: tuple = (0.0, 0.0, -1.0)
    size: tuple = (1.0, 1.0)
    file: Path | None = None
    scale: float = 1.0
    rotate_deg: float = 0.0
    sun_direction: tuple = (0.0, 0.0, 1.0)
    turbidity: float = 3.0
    albedo: float = 0.3
    sun_scale: float = 1.0
    sky_scale: float = 1.0
    up: tuple = (0.0, 0.0, 1.0)  # not a YAML key: the world's up that an envmap's zenith turns to (a dataset's)


@dataclass
class MeshSpec:
    key: str
    file: Path | None = None
    shape: str | None = None   # a procedural shape, or "mitsuba" for a mesh of an XML scene
    params: dict = field(default_factory=dict)
    repair: bool = False
    part: str | None = None    # one group/object of an OBJ file
    split: bool = False        # one scene object per group/object of an OBJ file


@dataclass
class TransformConfig:
    translate: tuple = (0.0, 0.0, 0.0)
    rotate_axis: tuple = (0.0, 0.0, 1.0)
    rotate_deg: float = 0.0
    scale: tuple = (1.0, 1.0, 1.0)


@dataclass
class BitmapConfig:
    """A bitmap texture as a BSDF parameter value (Mitsuba's ``bitmap``): an image file (PNG, EXR,
    JPG) looked up at the mesh's UV coordinates, or (``data``, not a YAML key) an in-memory
    (H, W, 3) linear float image, e.g. the texture an optimisation is recovering."""
    file: Path | None = None
    filter_type: str = "bilinear"
    wrap_mode: str = "repeat"
    raw: bool = False
    data: Any = None


@dataclass
class BsdfConfig:
    type: str = "diffuse"
    params: dict = field(default_factory=dict)


@dataclass
class ObjectConfig:
    name: str
    mesh: MeshSpec
    key: str
    transform: TransformConfig = field(default_factory=TransformConfig)
    bsdf: BsdfConfig = field(default_factory=BsdfConfig)
    edges: bool = True
    smooth: bool = False
    bsdf_given: bool = True     # False: the default BSDF, which an OBJ part's MTL colour replaces (then True)
    parts: dict = field(default_factory=dict)  # split objects: part name -> {bsdf, edges, smooth} overrides


@dataclass
class MitsubaSource:
    """``scene: {mitsuba: scene.xml}``: a Mitsuba 3 XML scene (read by :mod:`psdr_cli.mitsuba_scene`).

    ``params``: ``$name`` substitutions; ``film``: (width, height) replacing the XML film's size;
    ``edges``: {shape id: bool} overrides; ``up``: the scene's up axis (default of camera ``up``
    and of rotation axes); ``up_given``: whether the file set it. ``digest`` is filled when the
    experiment is loaded (:mod:`psdr_cli.experiment`), once the XML has been read."""
    file: Path
    params: dict = field(default_factory=dict)
    film: tuple | None = None
    edges: dict = field(default_factory=dict)
    up: tuple = (0.0, 0.0, 1.0)
    up_given: bool = False
    cameras_given: bool = False
    max_depth_given: bool = False
    digest: str = ""


@dataclass
class SceneConfig:
    width: int
    height: int
    max_depth: int
    cameras: list
    emitters: list
    objects: list
    mitsuba: MitsubaSource | None = None   # an XML scene: cameras, emitters, objects come from it
    hide_background: bool = False          # camera rays that leave the scene see black (a dataset's masked views)


@dataclass
class ParameterConfig:
    kind: str  # translate | rotate | scale | envmap_rotate
    object: str | None = None
    axis: tuple = (1.0, 0.0, 0.0)
    camera: int | None = None  # translate/rotate this camera (view index) instead of an object


@dataclass
class GridConfig:
    resolution: tuple = (64, 8, 8)
    samples_per_cell: int = 64


@dataclass
class KdTreeConfig:
    samples_per_node: int = 32
    initial_samples: int = 0         # 0: auto, half of one boundary pass's lanes in [131072, 262144]
    refine_ratio: float = 0.0        # second batch (drawn from the first tree) / initial_samples
    interval_share: float = 0.1
    technique_share: float = 0.3     # MIS: share of the techniques' common u1 (edge) profile
    threshold: float = 0.002
    max_depth: int = 24
    max_leaves: int = 65536


@dataclass
class ChainConfig:
    max_turn: float = 60.0     # degrees: a chain stops at a sharper turn
    max_length: int = 1024     # edges per chain


@dataclass
class EstimatorConfig:
    spp: int = 64
    primary_spp: int = 16
    boundary_spp: int = 16
    terms: tuple = ("interior", "primary", "direct", "indirect")
    sampling: str = "mis"
    guiding: str = "auto"
    passes: int = 1
    guide_epsilon: float = 0.05
    edge_sort: bool = False
    primary_sampling: str = "length"       # length | jump: primary-term edge density (estimators/primary.py)
    engine: str = "psdr"                   # psdr | mitsuba (optimize only)
    mitsuba_integrator: str | None = None  # default: direct_projective, prb_projective when max_depth > 2
    mitsuba_spp: int = 16                  # samples per pixel of Mitsuba's render (the tutorial's 16)
    mitsuba_shadows: bool = False          # Mitsuba's indirect-visibility term (sppi); the recipe turns it off
    chains: ChainConfig = field(default_factory=ChainConfig)
    grid: GridConfig = field(default_factory=GridConfig)
    kdtree: KdTreeConfig = field(default_factory=KdTreeConfig)


@dataclass
class RemeshConfig:
    method: str = "instant"          # instant (field-aligned) | isotropic | none
    initial: int = 1500              # vertices of the remeshed initial shape
    at: tuple = ()                   # iterations at which to remesh again
    vertices: tuple = ()             # vertex budget at each of those iterations


@dataclass
class DatasetConfig:
    """``optimize.target.dataset``: photographs and their cameras (:mod:`psdr_cli.datasets`)."""
    path: Path
    key: str                               # key path in the file, for error messages
    format: str = "auto"                   # auto | blender | transforms | colmap
    images: Path | None = None             # colmap: the image folder (default: <path>/images, <path>/../../images)
    masks: Path | None = None              # colmap: a folder of mask PNGs named after the images
    downsample: int = 1                    # area-average factor applied to every image (and its intrinsics)
    linear: bool = False                   # PNG/JPEG values are linear already (default: sRGB-encoded)
    holdout_every: int | None = None       # None: the dataset's own splits; k: every k-th frame is held out
    background: str = "auto"               # auto (hidden when the views have masks) | hidden | visible
    silhouette: float = 1.0                # weight of the silhouette loss mean|C − M| of masked views (0: off)
    up: tuple | None = None                # the dataset world's up axis (None: found from the cameras)
    frame: tuple | None = None             # not a YAML key: (s, c) of the normalised frame, filled when loaded
    split: str = "train"                   # not a YAML key: the views the scene's cameras are (train | test)


@dataclass
class EnvmapUnknown:
    """``optimize.envmap``: the scene's ``envmap`` emitter's lat-long map as an unknown, optimised
    as log-radiance x (the map is scale · exp(x), positive by construction)."""
    resolution: tuple = (32, 16)           # (W, H) texels of the lat-long map
    init: tuple | None = None              # constant radiance (r, g, b); None: the scene map's mean
    init_file: Path | None = None          # an EXR lat-long map, resampled to the resolution
    learning_rate: float = 0.05            # Adam step on the log-radiance
    smoothness: float = 0.0                # weight of the Laplacian prior on the log-radiance
    mean: str = "auto"                     # fixed | free | auto (fixed when optimize.albedo is set)


#: ``optimize.material`` unknowns: (clamp range, {BSDF type: Mitsuba parameter}).
MATERIAL_UNKNOWNS = {
    "roughness": ((0.01, 1.0), {"principled": "roughness", "roughconductor": "alpha", "roughdielectric": "alpha"}),
    "metallic": ((0.0, 1.0), {"principled": "metallic"}),
    "specular": ((0.0, 1.0), {"principled": "specular"}),
}

# Mitsuba's defaults of those parameters (a texture starts from them when neither optimize.material.NAME.init
# nor the BSDF gives a value)
MATERIAL_DEFAULTS = {"roughness": 0.5, "alpha": 0.1, "metallic": 0.0, "specular": 0.5}


def needs_uv(opt) -> bool:
    """Whether the shape being optimised needs texture coordinates: a texture is recovered
    (``optimize.albedo.texture`` or ``optimize.material.NAME.texture``)."""
    return bool((opt.albedo and opt.albedo_texture is not None) or any(m.texture is not None for m in opt.material))


def unwrap_size(opt) -> tuple:
    """(W, H) a UV atlas is laid out for: the largest texture being recovered (:func:`needs_uv`)."""
    sizes = ([opt.albedo_texture] if opt.albedo and opt.albedo_texture is not None else []) + \
        [m.texture for m in opt.material if m.texture is not None]
    return max(sizes, key=lambda s: s[0] * s[1])


@dataclass
class MaterialUnknown:
    """One scalar BSDF parameter of ``optimize.material`` (:data:`MATERIAL_UNKNOWNS`)."""
    name: str
    init: float | None = None              # default: the object's BSDF value
    learning_rate: float = 0.02
    texture: tuple | None = None           # (W, H): a one-channel bitmap instead of one value


@dataclass
class OptimizeConfig:
    object: str
    target_images: str | None = None       # glob of EXR files written by `psdr render`
    target_dataset: DatasetConfig | None = None  # photographs with their cameras
    target_mesh: MeshSpec | None = None    # ground-truth mesh (default: the object's own mesh)
    target_spp: int = 256
    init: MeshSpec | None = None           # initial shape (default: a sphere around the target)
    init_transform: TransformConfig = field(default_factory=TransformConfig)
    remesh: RemeshConfig = field(default_factory=RemeshConfig)
    iterations: int = 200
    batch_size: int = 4
    learning_rate: float = 0.1             # Adam step on the large-steps latent (docs/optimize.md, "Defaults")
    learning_rate_final: float | None = None  # geometric decay to this after the last remesh (None: constant)
    lambda_: tuple = (20.0,)               # LargeSteps λ: one value, or one per remesh stage (1 + len(remesh.at))
    downsample: tuple = (1,)               # image downsampling factor per remesh stage (coarse to fine)
    guide_every: int = 10
    adjoint_spp: int = 0                   # samples of the separate primal render the L1 sign comes from (0: the AD image's own)
    checkpoint_every: int = 50
    preview_views: tuple = (0,)
    albedo: bool = False
    albedo_init: tuple | None = None       # default: the object's BSDF value
    albedo_learning_rate: float = 0.02
    albedo_texture: tuple | None = None    # (W, H): recover a bitmap texture instead of one colour
    envmap_rotation: bool = False
    envmap_axis: tuple = (0.0, 0.0, 1.0)
    envmap_init_deg: float = 0.0
    envmap_learning_rate: float = 0.01
    envmap: EnvmapUnknown | None = None    # the environment map itself as an unknown
    material: tuple = ()                   # of MaterialUnknown: roughness, metallic, specular
    seconds: float | None = None           # wall-clock budget of the optimisation (equal-time runs)
    outlier_clip: str | float = "auto"     # each gradient scaled to at most c times its running norm (outlier_clip.py)
    variants: tuple = ()                   # of Variant: one run folder each, <output>/<name>/<label>
    target_seed: int | None = None         # not a YAML key: a variant's targets use its base experiment's seed


@dataclass
class Variant:
    """One estimator variant: a run of an ablation (``optimize.variants``) or an entry of a
    comparison (``compare.variants``). ``None`` keeps the experiment's value. ``seed`` gives a
    run another seed (replicate runs; the targets do not depend on it); ``passes`` gives a
    comparison entry a fixed number of passes (equal samples) instead of the time budget;
    ``learning_rate`` and ``lambda`` give a run its own step (a sweep of step sizes per estimator)."""
    label: str
    guiding: str | None = None
    sampling: str | None = None
    edge_sort: bool | None = None
    seed: int | None = None
    passes: int | None = None
    engine: str | None = None
    learning_rate: float | None = None     # a run's own Adam step (step-size sweeps)
    lambda_: tuple | None = None           # a run's own LargeSteps λ, one value or one per stage


@dataclass
class CompareConfig:
    variants: list                       # of Variant (guiding, sampling, edge_sort always set)
    terms: tuple = ("direct",)
    view: int = 0
    budget_seconds: float = 6.0
    trials: int = 2
    reference_passes: int = 1024


@dataclass
class EvaluateConfig:
    reference: Path | None = None
    samples: int = 100_000
    seed: int = 0


#: Folders of ``<output>/<name>/`` that commands other than ``psdr optimize`` write.
COMMAND_FOLDERS = ("render", "grad", "compare", "guide_stats")


@dataclass
class Experiment:
    """A parsed experiment file. ``base_dir`` is the folder relative paths are resolved against."""
    file: Path
    name: str
    output: Path
    seed: int
    variant: str
    scene: SceneConfig
    parameter: ParameterConfig | None
    estimator: EstimatorConfig
    optimize: OptimizeConfig | None = None
    evaluate: EvaluateConfig | None = None
    compare: CompareConfig | None = None

    @property
    def base_dir(self) -> Path:
        return self.file.parent

    @property
    def run_dir(self) -> Path:
        return self.output / self.name

    def command_dir(self, command: str, out: Path | None = None) -> Path:
        """Output folder of a command: ``<output>/<name>/<command>`` (``out`` replaces ``output``;
        ``command`` one of :data:`COMMAND_FOLDERS`)."""
        return (Path(out).resolve() / self.name if out else self.run_dir) / command


# --------------------------------------------------------------------------------------------
# Sections
# --------------------------------------------------------------------------------------------
BSDF_PARAMS = {
    "diffuse": ("reflectance",),
    "roughconductor": ("material", "eta", "k", "specular_reflectance", "distribution", "alpha",
                       "alpha_u", "alpha_v", "sample_visible"),
    "roughdielectric": ("int_ior", "ext_ior", "specular_reflectance", "specular_transmittance",
                        "distribution", "alpha", "alpha_u", "alpha_v", "sample_visible"),
    "principled": ("base_color", "roughness", "metallic", "specular", "spec_tint", "anisotropic",
                   "sheen", "sheen_tint", "clearcoat", "clearcoat_gloss", "spec_trans", "eta"),
}
SHAPE_PARAMS = {
    "sphere": {"radius": number(positive=True, maximum=MAX_COORD), "subdivisions": integer(0, 8),
               "resolution": integer(3, 2048), "uv": boolean},
    "plane": {"size": None},
    "cube": {"size": None},
    "torus": {"major_radius": number(positive=True, maximum=MAX_COORD),
              "minor_radius": number(positive=True, maximum=MAX_COORD),
              "major_sections": integer(3, 4096), "minor_sections": integer(3, 4096)},
    "bunny": {"size": number(positive=True, maximum=MAX_COORD), "faces": integer(100, 1_000_000)},
    "eared_blob": {"radius": number(positive=True, maximum=MAX_COORD),
                   "ear_length": number(minimum=0, maximum=MAX_COORD), "ear_width": number(positive=True, maximum=1),
                   "ear_tilt_deg": number(minimum=-80, maximum=80), "subdivisions": integer(2, 7)},
    "grooved_block": {"size": None, "groove_radius": number(positive=True, maximum=MAX_COORD),
                      "segments": integer(2, 4096)},
}
#: Physical range of the numeric BSDF parameters (per channel); the others only need to be finite.
BSDF_RANGES = {name: (0.0, 1.0) for name in (
    "reflectance", "specular_reflectance", "specular_transmittance", "base_color", "roughness", "metallic",
    "specular", "spec_tint", "anisotropic", "sheen", "sheen_tint", "clearcoat", "clearcoat_gloss", "spec_trans",
    "alpha", "alpha_u", "alpha_v")}
BSDF_RANGES.update({name: (1e-3, 10.0) for name in ("eta", "int_ior", "ext_ior")})
BSDF_RANGES["k"] = (0.0, 100.0)
#: Image formats a bitmap texture may be read from (by ``mi.Bitmap``).
BITMAP_FORMATS = (".png", ".exr", ".jpg", ".jpeg")
BITMAP_FILTERS = ("bilinear", "nearest")
BITMAP_WRAPS = ("repeat", "mirror", "clamp")


def parse_bitmap(value, where) -> BitmapConfig:
    """``{type: bitmap, file: image, filter_type, wrap_mode, raw}``; ``file`` is relative to the
    experiment file and must exist, be readable and be a PNG, EXR or JPG image (its texels are
    checked when the scene is built)."""
    sec = Section(value, where)
    sec.get("type", choice("bitmap"))
    file = sec.get("file", path_relative_to(Path(where.file).resolve().parent))
    b = BitmapConfig(file=file,
                     filter_type=sec.get("filter_type", choice(*BITMAP_FILTERS), "bilinear"),
                     wrap_mode=sec.get("wrap_mode", choice(*BITMAP_WRAPS), "repeat"),
                     raw=sec.get("raw", boolean, False))
    sec.done()
    w = where.child("file")
    if file.suffix.lower() not in BITMAP_FORMATS:
        raise w.fail(f"unsupported image format '{file.suffix}' (expected {', '.join(BITMAP_FORMATS)})")
    if not file.is_file():
        raise w.fail(f"texture file not found: {file}")
    if not os.access(file, os.R_OK):
        raise w.fail(f"texture file is not readable: {file}")
    return b


def _bsdf_value(value, where):
    if isinstance(value, str):
        return value
    if isinstance(value, bool):
        return value
    name = where.path.rsplit(".", 1)[-1]
    lo, hi = BSDF_RANGES.get(name, (-MAX_COORD, MAX_COORD))
    if isinstance(value, (int, float)):
        v = number()(value, where)
        values = [v]
    elif isinstance(value, list):
        v = vector(3, bound=FLOAT32_MAX)(value, where)
        values = list(v)
    elif isinstance(value, dict):
        return parse_bitmap(value, where)
    else:
        raise where.fail(f"expected a number, a list of 3 numbers, a string or a bitmap "
                         f"{{type: bitmap, file: ...}}, got {_describe(value)}")
    if min(values) < lo or max(values) > hi:
        raise where.fail(f"expected values in [{lo:g}, {hi:g}], got {_describe(value)}")
    return v


def parse_bsdf(value, where) -> BsdfConfig:
    sec = Section(value, where)
    kind = sec.get("type", choice(*BSDF_PARAMS))
    params = {}
    for name in BSDF_PARAMS[kind]:
        v = sec.get(name, _bsdf_value, None)
        if v is not None:
            params[name] = v
    sec.done()
    return BsdfConfig(kind, params)


def parse_mesh(base: Path) -> Parser:
    def parse(value, where):
        sec = Section(value, where)
        if sec.has("file") and sec.has("shape"):
            raise where.fail("give either 'file' or 'shape', not both")
        repair = sec.get("repair", boolean, False)
        if sec.has("file"):
            spec = MeshSpec(where.path + ".file", file=sec.get("file", path_relative_to(base)), repair=repair)
            spec.part = sec.get("part", string, None)
            spec.split = sec.get("split", boolean, False)
            sec.done()
            if (spec.part is not None or spec.split) and spec.file.suffix.lower() != ".obj":
                raise where.child("part" if spec.part is not None else "split").fail(
                    f"parts need an .obj file (groups 'g' / objects 'o'), got '{spec.file.name}'")
            if spec.part is not None and spec.split:
                raise where.fail("give either 'part' or 'split: true', not both")
            return spec
        shape = sec.get("shape", choice(*SHAPE_PARAMS), None)
        if shape is None:
            raise where.fail("expected 'file: <path.ply|.obj>' or 'shape: " + "|".join(SHAPE_PARAMS) + "'")
        params = {}
        for name, parser in SHAPE_PARAMS[shape].items():
            if parser is None:  # size of a plane (w, h), a cube or a grooved block (x, y, z)
                parser = _plane_size if shape == "plane" else scale3
            v = sec.get(name, parser, None)
            if v is not None:
                params[name] = v
        sec.done()
        return MeshSpec(where.path, shape=shape, params=params, repair=repair)
    return parse


def object_name(value, where):
    """An object's name: one that cannot be taken for psdr's own ids (:func:`name_problem`)."""
    name = string(value, where)
    problem = name_problem(name)
    if problem:
        raise where.fail(problem)
    return name


def _plane_size(value, where):
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value, value]
    return vector(2, positive=True)(value, where)


def parse_transform(value, where) -> TransformConfig:
    sec = Section(value, where)
    t = TransformConfig()
    t.translate = sec.get("translate", vector(3), t.translate)
    if sec.has("rotate"):
        rot = Section(sec.get("rotate", lambda v, w: v), where.child("rotate"))
        t.rotate_axis = _unit(rot.get("axis", vector(3, nonzero=True)))
        t.rotate_deg = rot.get("angle_deg", number())
        rot.done()
    t.scale = sec.get("scale", scale3, t.scale)
    sec.done()
    return t


def parse_object(base: Path) -> Parser:
    def parse(value, where):
        sec = Section(value, where)
        obj = ObjectConfig(
            name=sec.get("name", object_name),
            mesh=sec.get("mesh", parse_mesh(base)),
            key=where.path,
            transform=sec.get("transform", parse_transform, TransformConfig()),
            bsdf=sec.get("bsdf", parse_bsdf, BsdfConfig("diffuse", {"reflectance": (0.5, 0.5, 0.5)})),
            edges=sec.get("edges", boolean, True),
            smooth=sec.get("smooth", boolean, False),
            bsdf_given=sec.has("bsdf"),
        )
        if sec.has("parts"):
            if not obj.mesh.split:
                raise where.child("parts").fail("only allowed with 'mesh: {file: x.obj, split: true}'")
            obj.parts = sec.get("parts", parse_parts)
        sec.done()
        return obj
    return parse


def parse_parts(value, where) -> dict:
    """``parts: {NAME: {bsdf, edges, smooth}}``: per-part overrides of a split OBJ object."""
    if not isinstance(value, dict):
        raise where.fail(f"expected a mapping of part names, got {_describe(value)}")
    out = {}
    for name, entry in value.items():
        w = where.child(str(name))
        sec = Section(entry, w)
        out[str(name)] = {k: v for k, v in (("bsdf", sec.get("bsdf", parse_bsdf, None)),
                                            ("edges", sec.get("edges", boolean, None)),
                                            ("smooth", sec.get("smooth", boolean, None))) if v is not None}
        sec.done()
    return out


EMITTER_TYPES = ("area", "envmap", "sky", "constant")


def parse_emitter(base: Path) -> Parser:
    def parse(value, where):
        sec = Section(value, where)
        kind = sec.get("type", choice(*EMITTER_TYPES))
        em = EmitterConfig(type=kind, key=where.path)
        if kind == "area":
            em.center = sec.get("center", vector(3))
            em.normal = _unit(sec.get("normal", vector(3, nonzero=True)))
            em.size = sec.get("size", vector(2, positive=True))
            em.radiance = sec.get("radiance", color)
        elif kind == "envmap":
            em.file = sec.get("file", path_relative_to(base))
            em.scale = sec.get("scale", number(minimum=0, maximum=MAX_RADIANCE), 1.0)
            em.rotate_deg = sec.get("rotate_deg", number(), 0.0)
        elif kind == "sky":
            em.sun_direction = _unit(sec.get("sun_direction", vector(3, nonzero=True)))
            em.turbidity = sec.get("turbidity", number(minimum=1, maximum=10), 3.0)
            em.albedo = sec.get("albedo", number(minimum=0, maximum=1), 0.3)
            em.sun_scale = sec.get("sun_scale", number(minimum=0, maximum=MAX_RADIANCE), 1.0)
            em.sky_scale = sec.get("sky_scale", number(minimum=0, maximum=MAX_RADIANCE), 1.0)
            em.rotate_deg = sec.get("rotate_deg", number(), 0.0)
        else:
            em.radiance = sec.get("radiance", color)
        sec.done()
        return em
    return parse


#: Largest |offset| of ``principal_point`` (film widths / heights): the principal point within
#: half a film beyond the film's edge.
MAX_PRINCIPAL_OFFSET = 1.0


def principal_point(value, where):
    """``principal_point: [ox, oy]``: Mitsuba's principal point offset, fractions of the film's
    width and height (not pixels), each within ±:data:`MAX_PRINCIPAL_OFFSET`."""
    ok = isinstance(value, (list, tuple)) and len(value) == 2 and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    if not ok:
        raise where.fail(f"expected [ox, oy], two numbers (fractions of the film width and height), "
                         f"got {_describe(value)}")
    if not all(finite(v) and abs(v) <= MAX_PRINCIPAL_OFFSET for v in value):
        raise where.fail(f"expected two finite numbers within ±{MAX_PRINCIPAL_OFFSET:g} (fractions of the film "
                         f"width and height, not pixels), got {_describe(list(value))}")
    return tuple(float(v) for v in value)


def _check_camera(cam: CameraConfig, where: Where) -> CameraConfig:
    d = [t - o for t, o in zip(cam.target, cam.origin)]
    length = math.sqrt(sum(c * c for c in d))
    if length < 1e-9 * (1 + max(abs(c) for c in cam.origin)):
        raise where.fail(f"origin and target are the same point {list(cam.origin)}; the camera needs a view direction")
    cross = (d[1] * cam.up[2] - d[2] * cam.up[1], d[2] * cam.up[0] - d[0] * cam.up[2],
             d[0] * cam.up[1] - d[1] * cam.up[0])
    if math.sqrt(sum(c * c for c in cross)) < 1e-6 * length * math.sqrt(sum(c * c for c in cam.up)):
        raise where.fail("'up' is parallel to the view direction (target - origin)")
    return cam


def orbit_cameras(count, radius, elevation_deg, azimuth_deg, target, fov, up=(0.0, 0.0, 1.0)):
    """``count`` cameras evenly spaced in azimuth on a circle of ``radius`` around ``target``.

    Position_i = target + radius·(cos e·cos a_i·X + cos e·sin a_i·Y + sin e·Up), a_i = a_0 + 360°·i/count,
    with (X, Y, Up) a right-handed frame around ``up``.
    """
    upn = _unit(up)
    ref = (1.0, 0.0, 0.0) if abs(upn[0]) < 0.9 else (0.0, 1.0, 0.0)
    dot = sum(a * b for a, b in zip(ref, upn))
    x = _unit(tuple(r - dot * u for r, u in zip(ref, upn)))
    y = (upn[1] * x[2] - upn[2] * x[1], upn[2] * x[0] - upn[0] * x[2], upn[0] * x[1] - upn[1] * x[0])
    e = math.radians(elevation_deg)
    cams = []
    for i in range(count):
        a = math.radians(azimuth_deg + 360.0 * i / count)
        dirv = [math.cos(e) * math.cos(a) * x[k] + math.cos(e) * math.sin(a) * y[k] + math.sin(e) * upn[k]
                for k in range(3)]
        origin = tuple(target[k] + radius * dirv[k] for k in range(3))
        cams.append(CameraConfig(origin=origin, target=tuple(target), up=upn, fov=fov))
    return cams


def parse_cameras(value, where, up=(0.0, 0.0, 1.0)) -> list:
    """A list of cameras and ``orbit:`` rings; a single ``{orbit: {...}}`` mapping is accepted
    as a one-item list. ``up`` is the default up direction (the scene's up axis)."""
    if isinstance(value, dict) and set(value) == {"orbit"}:
        value = [value]
    items = list_of(lambda v, w: (v, w), min_len=1)(value, where)
    cams = []
    for v, w in items:
        sec = Section(v, w)
        if sec.has("orbit"):
            orb = Section(sec.get("orbit", lambda x, _: x), w.child("orbit"))
            ring = orbit_cameras(
                count=orb.get("count", integer(1, 4096)),
                radius=orb.get("radius", number(positive=True, maximum=MAX_COORD)),
                elevation_deg=orb.get("elevation_deg", number(minimum=-89.9, maximum=89.9), 20.0),
                azimuth_deg=orb.get("azimuth_deg", number(), 0.0),
                target=orb.get("target", vector(3), (0.0, 0.0, 0.0)),
                fov=orb.get("fov", number(positive=True, maximum=179), 40.0),
                up=orb.get("up", vector(3, nonzero=True), up),
            )
            orb.done()
            sec.done()
            cams.extend(ring)
            continue
        cam = CameraConfig(
            origin=sec.get("origin", vector(3)),
            target=sec.get("target", vector(3)),
            up=sec.get("up", vector(3, nonzero=True), up),
            fov=sec.get("fov", number(positive=True, maximum=179), 40.0),
            principal_point=sec.get("principal_point", principal_point, (0.0, 0.0)),
        )
        sec.done()
        cams.append(_check_camera(cam, w))
    return cams


def _xml_param(value, where):
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float, str)):
        return str(value)
    raise where.fail(f"expected a number, a string or true/false, got {_describe(value)}")


def parse_mitsuba_scene(sec: Section, where: Where, base: Path) -> SceneConfig:
    """``scene: {mitsuba: file.xml, params, film, max_depth, cameras, up, objects}``. The XML
    itself is read later (it needs Mitsuba): its sensors, emitters and shapes fill the scene."""
    file = sec.get("mitsuba", path_relative_to(base))
    if file.suffix.lower() != ".xml":
        raise where.child("mitsuba").fail(f"expected a Mitsuba 3 scene file (.xml), got '{file.name}'")
    if not file.is_file():
        raise where.child("mitsuba").fail(f"file not found: {file}")
    src = MitsubaSource(file=file)
    params = sec.get("params", lambda v, w: v, {})
    if not isinstance(params, dict):
        raise where.child("params").fail(f"expected a mapping of $name: value, got {_describe(params)}")
    src.params = {str(k): _xml_param(v, where.child("params").child(str(k))) for k, v in params.items()}
    if sec.has("film"):
        film = Section(sec.get("film", lambda v, _: v), where.child("film"))
        src.film = (film.get("width", integer(1, MAX_FILM)), film.get("height", integer(1, MAX_FILM)))
        film.done()
    src.up_given = sec.has("up")
    src.up = _unit(sec.get("up", vector(3, nonzero=True), src.up))
    src.cameras_given = sec.has("cameras")
    src.max_depth_given = sec.has("max_depth")
    objects = sec.get("objects", lambda v, w: v, {})
    if not isinstance(objects, dict):
        raise where.child("objects").fail(f"expected a mapping of XML shape ids to {{edges: ...}}, got "
                                          f"{_describe(objects)}")
    for name, entry in objects.items():
        o = Section(entry, where.child("objects").child(str(name)))
        src.edges[str(name)] = o.get("edges", boolean, True)
        o.done()
    scene = SceneConfig(
        width=src.film[0] if src.film else 0, height=src.film[1] if src.film else 0,
        max_depth=sec.get("max_depth", integer(1), 2),
        cameras=sec.get("cameras", lambda v, w: parse_cameras(v, w, src.up), []),
        emitters=[], objects=[], mitsuba=src)
    sec.done()
    return scene


def parse_scene(base: Path) -> Parser:
    def parse(value, where):
        sec = Section(value, where)
        if sec.has("mitsuba"):
            return parse_mitsuba_scene(sec, where, base)
        film = Section(sec.get("film", lambda v, _: v, {}), where.child("film"))
        width = film.get("width", integer(1, MAX_FILM), 128)
        height = film.get("height", integer(1, MAX_FILM), 128)
        film.done()
        scene = SceneConfig(
            width=width, height=height,
            max_depth=sec.get("max_depth", integer(1, MAX_DEPTH), 2),
            cameras=sec.get("cameras", parse_cameras, None),  # None: from optimize.target.dataset
            emitters=sec.get("emitters", list_of(parse_emitter(base), min_len=1)),
            objects=sec.get("objects", list_of(parse_object(base)), []),
        )
        sec.done()
        check_scene(scene, where.file)
        return scene
    return parse


def check_scene(scene: SceneConfig, file: str):
    """Unique object names and at most one environment emitter (also once an XML scene has been read)."""
    names = set()
    for obj in scene.objects:
        if obj.name in names:
            raise Where(file, obj.key + ".name").fail(f"duplicate object name '{obj.name}'")
        names.add(obj.name)
    n_env = sum(e.type in ("envmap", "sky", "constant") for e in scene.emitters)
    if n_env > 1:
        raise Where(file, "scene.emitters").fail("at most one environment emitter (envmap, sky or constant) is allowed")


PARAMETER_KINDS = ("translate", "rotate", "scale", "envmap_rotate")
DEFAULT_AXIS = {"translate": (1.0, 0.0, 0.0), "rotate": (0.0, 0.0, 1.0), "scale": (1.0, 1.0, 1.0),
                "envmap_rotate": (0.0, 0.0, 1.0)}


def parse_parameter(value, where, up=(0.0, 0.0, 1.0)) -> ParameterConfig:
    """The ``parameter:`` section; rotations default to the axis ``up`` (the scene's up axis)."""
    sec = Section(value, where)
    kind = sec.get("kind", choice(*PARAMETER_KINDS))
    obj = sec.get("object", string, None)
    camera = sec.get("camera", integer(0), None)
    if camera is not None and obj is not None:
        raise where.child("camera").fail("give either 'object' or 'camera', not both")
    if camera is not None and kind not in ("translate", "rotate"):
        raise where.child("camera").fail(f"a camera can only be translated or rotated, not '{kind}'")
    if kind != "envmap_rotate" and obj is None and camera is None:
        raise where.child("object").fail(f"missing (required for kind '{kind}'; or 'camera: INDEX')")
    if kind == "envmap_rotate" and obj is not None:
        raise where.child("object").fail("not allowed for kind 'envmap_rotate'")
    default = tuple(up) if kind in ("rotate", "envmap_rotate") else DEFAULT_AXIS[kind]
    axis = sec.get("axis", vector(3, nonzero=True), default)
    sec.done()
    return ParameterConfig(kind=kind, object=obj, axis=axis if kind == "scale" else _unit(axis), camera=camera)


def check_paths(spp: int, width: int, height: int, fail) -> int:
    """``spp`` if one image of ``width × height`` pixels at ``spp`` samples per pixel stays within
    :data:`MAX_SPP` and :data:`MAX_PATHS`; else ``fail(message)`` is raised."""
    if spp > MAX_SPP:
        raise fail(f"{spp} samples per pixel exceed the limit of {MAX_SPP} (a resource limit)")
    if spp * width * height > MAX_PATHS:
        raise fail(f"{spp} samples per pixel × {width}×{height} pixels = {spp * width * height:.3g} paths per image "
                   f"exceed the limit of {MAX_PATHS:.3g} (hours of rendering; a resource limit)")
    return spp


def option_spp(name: str, spp: int | None, width: int, height: int) -> int | None:
    """A ``--spp``-like command-line value: None, or a positive count within the limits."""
    if spp is None:
        return None
    if spp < 1:
        raise PsdrError(f"{name}: expected a positive number of samples per pixel, got {spp}")
    return check_paths(spp, width, height, lambda m: PsdrError(f"{name}: {m}"))


def option_count(name: str, value: int | None, minimum: int, maximum: int) -> int | None:
    """A count given on the command line (``--iterations``, ``--samples``): None, or an integer
    in [minimum, maximum] (0 is an error, not "the default")."""
    if value is not None and not minimum <= value <= maximum:
        raise PsdrError(f"{name}: expected an integer in [{minimum}, {maximum}], got {value}")
    return value


def option_number(name: str, value: float | None, positive: bool = True) -> float | None:
    """A real-valued command-line option (e.g. ``--fd``): None, or finite in float32 (and > 0)."""
    if value is None:
        return None
    if not finite32(value) or (positive and value <= 0):
        raise PsdrError(f"{name}: expected a finite number{' > 0' if positive else ''}, got {value}")
    return value


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
                    if b < a:
                        raise PsdrError(f"--views: '{part}' is an empty range (expected FIRST-LAST with FIRST <= LAST, "
                                        f"e.g. 0-2)")
                    if not 0 <= a < count or b >= count:   # before the range is built: 0-9999999999
                        raise PsdrError(f"--views: view {a if not 0 <= a < count else b} does not exist "
                                        f"(the experiment has views 0..{count - 1})")
                    out.extend(range(a, b + 1))
                else:
                    out.append(int(part))
            except ValueError:
                raise PsdrError(f"--views: cannot read '{part}' (expected indices like 0,3 or 0-2)") from None
        views = out
    if not views:
        raise PsdrError(f"--views: no view given (expected indices like 0,3 or 0-2; the experiment has views "
                        f"0..{count - 1})")
    bad = [v for v in views if not 0 <= v < count]
    if bad:
        raise PsdrError(f"--views: view {bad[0]} does not exist (the experiment has views 0..{count - 1})")
    return sorted(set(views))


def parse_terms(terms) -> tuple | None:
    """Terms from a comma-separated string or a list, in :data:`TERMS` order (None: None)."""
    if terms is None:
        return None
    names = [t.strip() for t in terms.split(",")] if isinstance(terms, str) else list(terms)
    bad = [t for t in names if t not in TERMS]
    if bad or not names:
        raise PsdrError(f"--terms: unknown term '{bad[0] if bad else ''}' (expected a comma-separated "
                        f"subset of {','.join(TERMS)})")
    return tuple(t for t in TERMS if t in names)


def with_estimator(exp: "Experiment", **overrides) -> "Experiment":
    """The experiment with estimator keys replaced (``None`` values are ignored); values are
    checked like the YAML keys: ``sampling`` in :data:`SAMPLINGS`, ``guiding`` in :data:`GUIDINGS`,
    ``engine`` in :data:`ENGINES`."""
    allowed = {"sampling": SAMPLINGS, "guiding": GUIDINGS, "engine": ENGINES}
    changes = {k: v for k, v in overrides.items() if v is not None}
    for key, value in changes.items():
        if key.endswith("spp"):
            option_spp("--spp", value, exp.scene.width, exp.scene.height)
        if key in allowed and value not in allowed[key]:
            raise PsdrError(f"--{key.replace('_', '-')}: expected one of {', '.join(allowed[key])}, got '{value}'")
    return replace(exp, estimator=replace(exp.estimator, **changes)) if changes else exp


def _terms(value, where):
    if isinstance(value, str):
        value = [t.strip() for t in value.split(",") if t.strip()]
    terms = list_of(choice(*TERMS), min_len=1)(value, where)
    return tuple(t for t in TERMS if t in terms)


def parse_estimator(value, where) -> EstimatorConfig:
    sec = Section(value, where)
    est = EstimatorConfig()
    est.spp = sec.get("spp", integer(1, MAX_SPP), est.spp)
    est.primary_spp = sec.get("primary_spp", integer(1, MAX_SPP), est.primary_spp)
    est.boundary_spp = sec.get("boundary_spp", integer(1, MAX_SPP), est.boundary_spp)
    est.terms = sec.get("terms", _terms, est.terms)
    est.sampling = sec.get("sampling", choice(*SAMPLINGS), est.sampling)
    est.guiding = sec.get("guiding", choice(*GUIDINGS), est.guiding)
    est.passes = sec.get("passes", integer(1, MAX_PASSES), est.passes)
    est.guide_epsilon = sec.get("guide_epsilon", number(minimum=0, maximum=1), est.guide_epsilon)
    est.edge_sort = sec.get("edge_sort", boolean, est.edge_sort)
    est.primary_sampling = sec.get("primary_sampling", choice(*PRIMARY_SAMPLINGS), est.primary_sampling)
    est.engine = sec.get("engine", choice(*ENGINES), est.engine)
    for key in ("mitsuba_integrator", "mitsuba_spp", "mitsuba_shadows"):
        if sec.has(key) and est.engine != "mitsuba":
            raise where.child(key).fail("only used with 'engine: mitsuba' (add it, or remove this key)")
    est.mitsuba_integrator = sec.get("mitsuba_integrator", choice(*MITSUBA_INTEGRATORS), None)
    est.mitsuba_spp = sec.get("mitsuba_spp", integer(1, MAX_SPP), est.mitsuba_spp)
    est.mitsuba_shadows = sec.get("mitsuba_shadows", boolean, est.mitsuba_shadows)
    if sec.has("grid"):
        g = Section(sec.get("grid", lambda v, _: v), where.child("grid"))
        est.grid = GridConfig(
            resolution=tuple(int(r) for r in g.get("resolution", list_of(integer(1)), list(GridConfig.resolution))),
            samples_per_cell=g.get("samples_per_cell", integer(1), GridConfig.samples_per_cell))
        if len(est.grid.resolution) != 3:
            raise where.child("grid").child("resolution").fail("expected a list of 3 integers [nx, ny, nz]")
        cells = math.prod(est.grid.resolution)
        if cells > MAX_GRID_CELLS:
            raise where.child("grid").child("resolution").fail(
                f"{cells} cells exceed the limit of {MAX_GRID_CELLS} (nx·ny·nz; a resource limit)")
        if cells * est.grid.samples_per_cell > MAX_GRID_SAMPLES:
            raise where.child("grid").child("samples_per_cell").fail(
                f"{cells} cells × {est.grid.samples_per_cell} samples exceed the limit of {MAX_GRID_SAMPLES} "
                f"samples per guide build (a resource limit)")
        g.done()
    if sec.has("chains"):
        c = Section(sec.get("chains", lambda v, _: v), where.child("chains"))
        d = ChainConfig()
        est.chains = ChainConfig(max_turn=c.get("max_turn", number(minimum=0, maximum=180), d.max_turn),
                                 max_length=c.get("max_length", integer(1), d.max_length))
        c.done()
    if sec.has("kdtree"):
        k = Section(sec.get("kdtree", lambda v, _: v), where.child("kdtree"))
        d = KdTreeConfig()
        est.kdtree = KdTreeConfig(
            samples_per_node=k.get("samples_per_node", integer(4, 1 << 16), d.samples_per_node),
            initial_samples=k.get("initial_samples", integer(0, 1 << 22), d.initial_samples),
            refine_ratio=k.get("refine_ratio", number(minimum=0, maximum=16), d.refine_ratio),
            interval_share=k.get("interval_share", number(minimum=0, maximum=1), d.interval_share),
            technique_share=k.get("technique_share", number(minimum=0, maximum=1), d.technique_share),
            threshold=k.get("threshold", number(minimum=0), d.threshold),
            max_depth=k.get("max_depth", integer(1, 64), d.max_depth),
            max_leaves=k.get("max_leaves", integer(1, 1 << 22), d.max_leaves))
        k.done()
    sec.done()
    return est


def parse_remesh(value, where) -> RemeshConfig:
    sec = Section(value, where)
    r = RemeshConfig()
    r.method = sec.get("method", choice(*REMESH_METHODS), r.method)
    r.initial = sec.get("initial", integer(50, MAX_VERTICES), r.initial)
    r.at = tuple(sec.get("at", list_of(integer(1)), []))
    r.vertices = tuple(sec.get("vertices", list_of(integer(50, MAX_VERTICES)), []))
    sec.done()
    if len(r.at) != len(r.vertices):
        raise where.child("vertices").fail(f"expected one vertex budget per entry of 'at' ({len(r.at)}), "
                                           f"got {len(r.vertices)}")
    if list(r.at) != sorted(set(r.at)):
        raise where.child("at").fail("expected increasing iteration numbers")
    return r


def stage_count_error(where: Where, stages: int, got: int) -> ConfigError:
    return where.fail(f"expected one value, or a list of {stages} (one per remesh stage: the initial shape and "
                      f"each entry of remesh.at), got a list of {got}")


def per_stage(parse_item: Parser, stages: int) -> Parser:
    """One value for the whole run, or a list of one value per remesh stage (the initial shape,
    then each entry of ``remesh.at``), as a tuple."""
    def parse(value, where):
        if not isinstance(value, list):
            return (parse_item(value, where),)
        if len(value) != stages:
            raise stage_count_error(where, stages, len(value))
        return tuple(parse_item(v, where.child(i)) for i, v in enumerate(value))
    return parse


def _texture_size(value, where):
    """[W, H] of a texture being optimised: integers in 1..MAX_FILM."""
    if not isinstance(value, list) or len(value) != 2:
        raise where.fail(f"expected [width, height], got {_describe(value)}")
    return tuple(integer(1, MAX_FILM)(v, where.child(i)) for i, v in enumerate(value))


def _outlier_clip(value, where):
    """``auto``, ``off`` or a factor c ≥ 1 (gradient entries beyond c·√v̂ of Adam are clipped)."""
    if value in ("auto", "off"):
        return value
    if isinstance(value, str):
        raise where.fail(f"expected auto, off or a number >= 1, got '{value}'")
    return number(minimum=1)(value, where)


def parse_optimize(base: Path) -> Parser:
    def parse(value, where) -> OptimizeConfig:
        sec = Section(value, where)
        o = OptimizeConfig(object=sec.get("object", string, None))
        if sec.has("target"):
            t = Section(sec.get("target", lambda v, _: v), where.child("target"))
            given = [k for k in ("images", "mesh", "dataset") if t.has(k)]
            if len(given) > 1:
                raise where.child("target").fail(f"give one of 'images', 'mesh' and 'dataset', not {' and '.join(given)}")
            if t.has("object"):  # target: {object: NAME} is an alias of object: NAME
                name = t.get("object", string)
                if o.object is not None and o.object != name:
                    raise where.child("target").child("object").fail(
                        f"'{name}' contradicts optimize.object '{o.object}' (give one of them)")
                o.object = name
            o.target_images = t.get("images", string, None)
            if o.target_images is not None and not Path(o.target_images).is_absolute():
                o.target_images = str(base / o.target_images)
            o.target_mesh = t.get("mesh", parse_mesh(base), None)
            o.target_dataset = t.get("dataset", parse_dataset(base), None)
            o.target_spp = t.get("spp", integer(1, MAX_SPP), o.target_spp)
            t.done()
        if sec.has("init"):
            i = Section(sec.get("init", lambda v, _: v), where.child("init"))
            o.init = i.get("mesh", parse_mesh(base), None)  # null: the default sphere, as if absent
            o.init_transform = i.get("transform", parse_transform, TransformConfig())
            if o.init is None and i.has("transform"):
                raise where.child("init").child("transform").fail(
                    "needs init.mesh (the default initial shape is a sphere around the target's bounding box)")
            i.done()
        if o.object is None:
            raise where.child("object").fail("missing (the object to reconstruct; or target: {object: NAME})")
        o.remesh = sec.get("remesh", parse_remesh, RemeshConfig())
        o.iterations = sec.get("iterations", integer(1, MAX_ITERATIONS), o.iterations)
        o.batch_size = sec.get("batch_size", integer(1), o.batch_size)
        o.learning_rate = sec.get("learning_rate", number(positive=True), o.learning_rate)
        o.learning_rate_final = sec.get("learning_rate_final", number(positive=True), o.learning_rate_final)
        stages = 1 + len(o.remesh.at)
        o.lambda_ = sec.get("lambda", per_stage(number(minimum=0), stages), o.lambda_)
        o.downsample = sec.get("downsample", per_stage(integer(1, MAX_FILM), stages), o.downsample)
        o.guide_every = sec.get("guide_every", integer(1), o.guide_every)
        o.adjoint_spp = sec.get("adjoint_spp", integer(0, MAX_SPP), o.adjoint_spp)
        o.checkpoint_every = sec.get("checkpoint_every", integer(1), o.checkpoint_every)
        o.preview_views = tuple(sec.get("preview_views", list_of(integer(0), min_len=1), list(o.preview_views)))
        if sec.has("albedo"):
            a = Section(sec.get("albedo", lambda v, _: v), where.child("albedo"))
            o.albedo = True
            o.albedo_init = a.get("init", reflectance, None)
            o.albedo_learning_rate = a.get("learning_rate", number(positive=True), o.albedo_learning_rate)
            o.albedo_texture = a.get("texture", _texture_size, None)
            a.done()
        if sec.has("envmap_rotation"):
            e = Section(sec.get("envmap_rotation", lambda v, _: v), where.child("envmap_rotation"))
            o.envmap_rotation = True
            o.envmap_axis = e.get("axis", vector(3, nonzero=True), o.envmap_axis)
            o.envmap_init_deg = e.get("init_deg", number(), o.envmap_init_deg)
            o.envmap_learning_rate = e.get("learning_rate", number(positive=True), o.envmap_learning_rate)
            e.done()
        o.envmap = sec.get("envmap", parse_envmap_unknown(base), None)
        o.material = sec.get("material", parse_material, ())
        o.seconds = sec.get("seconds", number(positive=True), None)
        o.outlier_clip = sec.get("outlier_clip", _outlier_clip, o.outlier_clip)
        if sec.has("variants"):
            o.variants = tuple(sec.get("variants", list_of(run_variant_parser(stages), min_len=1)))
            unique_labels(o.variants, where)
        sec.done()
        return o
    return parse


ENVMAP_MEANS = ("auto", "fixed", "free")


def parse_envmap_unknown(base: Path) -> Parser:
    """``optimize.envmap: {resolution: [W, H], init: VALUE | [r, g, b] | FILE.exr, learning_rate,
    smoothness, mean}``; an init file's texels are checked once the experiment is loaded
    (:func:`psdr_cli.experiment.check_envmap_init`: OpenEXR is not imported here)."""
    def init_value(value, where):
        if isinstance(value, str):
            path = Path(value) if Path(value).is_absolute() else base / value
            if path.suffix.lower() != ".exr":
                raise where.fail(f"expected a radiance value, [r, g, b] or an EXR file, got {_describe(value)}")
            if not path.is_file():
                raise where.fail(f"file not found: {path}")
            return path
        return color(value, where)

    def parse(value, where) -> EnvmapUnknown:
        sec = Section(value, where)
        e = EnvmapUnknown()
        e.resolution = sec.get("resolution", _envmap_size, e.resolution)
        init = sec.get("init", init_value, None)
        if isinstance(init, Path):
            e.init_file = init
        elif init is not None:
            if max(init) <= 0:
                raise where.child("init").fail(f"expected a radiance > 0 (the map is optimised as its "
                                               f"logarithm), got {_describe(list(init))}")
            e.init = init
        e.learning_rate = sec.get("learning_rate", number(positive=True), e.learning_rate)
        e.smoothness = sec.get("smoothness", number(minimum=0), e.smoothness)
        e.mean = sec.get("mean", choice(*ENVMAP_MEANS), e.mean)
        sec.done()
        return e
    return parse


def _envmap_size(value, where):
    """[W, H] of an environment map being optimised: W in 2..4096, H in 2..2048."""
    if not isinstance(value, list) or len(value) != 2:
        raise where.fail(f"expected [width, height], got {_describe(value)}")
    return (integer(2, 4096)(value[0], where.child(0)), integer(2, 2048)(value[1], where.child(1)))


def parse_material(value, where) -> tuple:
    """``optimize.material: {roughness: {init, learning_rate, texture}, metallic: ..., specular: ...}``."""
    sec = Section(value, where)
    out = []
    for name, ((lo, hi), _) in MATERIAL_UNKNOWNS.items():
        if not sec.has(name):
            sec.used.add(name)
            continue
        w = where.child(name)
        m = Section(sec.get(name, lambda v, _: v), w)
        u = MaterialUnknown(name, init=m.get("init", number(minimum=lo, maximum=hi), None),
                            learning_rate=m.get("learning_rate", number(positive=True), 0.02),
                            texture=m.get("texture", _texture_size, None))
        m.done()
        out.append(u)
    sec.done()
    if not out:
        raise where.fail(f"expected at least one of {', '.join(MATERIAL_UNKNOWNS)}")
    return tuple(out)


DATASET_FORMATS = ("auto", "blender", "transforms", "colmap")
BACKGROUNDS = ("auto", "hidden", "visible")


def parse_dataset(base: Path) -> Parser:
    """``optimize.target.dataset``: a folder (or a ``transforms*.json`` file, or a COLMAP model
    folder) of photographs with their cameras; paths relative to the experiment file."""
    def folder(value, where):
        path = Path(string(value, where))
        return path if path.is_absolute() else base / path

    def parse(value, where) -> DatasetConfig:
        if isinstance(value, str):
            value = {"path": value}
        sec = Section(value, where)
        d = DatasetConfig(path=sec.get("path", folder), key=where.path)
        d.format = sec.get("format", choice(*DATASET_FORMATS), d.format)
        d.images = sec.get("images", folder, None)
        d.masks = sec.get("masks", folder, None)
        d.downsample = sec.get("downsample", integer(1, MAX_FILM), d.downsample)
        d.linear = sec.get("linear", boolean, d.linear)
        d.holdout_every = sec.get("holdout_every", integer(2, MAX_FILM), None)
        d.background = sec.get("background", choice(*BACKGROUNDS), d.background)
        d.silhouette = sec.get("silhouette", number(minimum=0), d.silhouette)
        d.up = sec.get("up", vector(3, nonzero=True), None)
        sec.done()
        if not d.path.exists():
            raise where.child("path").fail(f"not found: {d.path}")
        return d
    return parse


def parse_variant(value, where, guiding=None, sampling=None, edge_sort=None) -> Variant:
    """A variant mapping; the keyword arguments are the defaults of the keys it leaves out."""
    sec = Section(value, where)
    v = Variant(label=sec.get("label", string),
                guiding=sec.get("guiding", choice(*GUIDINGS), guiding),
                sampling=sec.get("sampling", choice(*SAMPLINGS), sampling),
                edge_sort=sec.get("edge_sort", boolean, edge_sort))
    return v, sec


#: Names a variant's run folder may not have: they are psdr's own entries of ``<output>/<name>/``.
RESERVED_LABELS = {**{c: f"psdr {c.replace('_', '-')}'s output folder" for c in COMMAND_FOLDERS},
                   "reference": "the report's reference.ply", "checkpoints": "a run's checkpoint folder",
                   "previews": "a run's preview folder", "targets": "a run's target images"}


def run_variant_parser(stages: int) -> Parser:
    """A run of ``optimize.variants``: estimator keys, ``seed``, ``engine``, and its own
    ``learning_rate`` and ``lambda`` (one value or one per remesh stage, of ``stages``)."""
    def parse(value, where) -> Variant:
        v, sec = parse_variant(value, where)
        if not v.label or "/" in v.label or v.label in (".", "..") or v.label != v.label.strip():
            raise where.child("label").fail(f"expected a plain folder name, got '{v.label}'")
        if v.label in RESERVED_LABELS:
            raise where.child("label").fail(f"'{v.label}' is taken ({RESERVED_LABELS[v.label]}); choose another label")
        v.seed = sec.get("seed", integer(0), None)
        v.engine = sec.get("engine", choice(*ENGINES), None)
        v.learning_rate = sec.get("learning_rate", number(positive=True), None)
        v.lambda_ = sec.get("lambda", per_stage(number(minimum=0), stages), None)
        sec.done()
        return v
    return parse


def parse_compare_variant(value, where) -> Variant:
    """A comparison entry: unguided, MIS and unsorted unless it says otherwise."""
    v, sec = parse_variant(value, where, guiding="none", sampling="mis", edge_sort=False)
    v.passes = sec.get("passes", integer(1), None)
    sec.done()
    return v


def unique_labels(variants, where):
    labels = [v.label for v in variants]
    if len(set(labels)) != len(labels):
        raise where.child("variants").fail("variant labels must be unique")


def parse_compare(value, where) -> CompareConfig:
    sec = Section(value, where)
    c = CompareConfig(variants=sec.get("variants", list_of(parse_compare_variant, min_len=1)))
    unique_labels(c.variants, where)
    c.terms = sec.get("terms", _terms, c.terms)
    c.view = sec.get("view", integer(0), c.view)
    c.budget_seconds = sec.get("budget_seconds", number(positive=True), c.budget_seconds)
    c.trials = sec.get("trials", integer(1), c.trials)
    c.reference_passes = sec.get("reference_passes", integer(2, MAX_PASSES), c.reference_passes)
    sec.done()
    return c


def parse_evaluate(base: Path) -> Parser:
    def parse(value, where) -> EvaluateConfig:
        sec = Section(value, where)
        e = EvaluateConfig()
        e.reference = sec.get("reference", path_relative_to(base), None)
        e.samples = sec.get("samples", integer(MIN_EVAL_SAMPLES, MAX_EVAL_SAMPLES), e.samples)
        e.seed = sec.get("seed", integer(0), e.seed)
        sec.done()
        return e
    return parse


# --------------------------------------------------------------------------------------------
# Entry points
# --------------------------------------------------------------------------------------------
def parse(data, file: Path, cwd: Path | None = None) -> Experiment:
    """Validate an already-loaded YAML document. ``file`` names the source in messages. The
    experiment as the file states it: its scene is read, and the checks that need object names
    run, by :func:`psdr_cli.experiment.parse_experiment`, which every user of an experiment loads with."""
    file = Path(file)
    where = Where(str(file), "")
    sec = Section(data, where)
    base = file.resolve().parent
    out = sec.get("output", string, "runs")
    name = sec.get("name", string, file.stem)
    scene = sec.get("scene", parse_scene(base))
    up = scene.mitsuba.up if scene.mitsuba else (0.0, 0.0, 1.0)
    exp = Experiment(
        file=file.resolve(),
        name=name,
        output=(Path(cwd or Path.cwd()) / out).resolve(),
        seed=sec.get("seed", integer(0), 0),
        variant=sec.get("variant", choice(*VARIANTS), "auto"),
        scene=scene,
        parameter=sec.get("parameter", lambda v, w: parse_parameter(v, w, up), None),
        estimator=sec.get("estimator", parse_estimator, EstimatorConfig()),
        optimize=sec.get("optimize", parse_optimize(base), None),
        evaluate=sec.get("evaluate", parse_evaluate(base), None),
        compare=sec.get("compare", parse_compare, None),
    )
    sec.done()
    check_camera_source(exp, data.get("scene"), where)
    if "/" in exp.name or exp.name in (".", ".."):
        raise where.child("name").fail(f"expected a plain folder name, got '{exp.name}'")
    return exp


def check_camera_source(exp: Experiment, scene_data, where: Where):
    """The cameras and film come from ``scene`` or, for a dataset, from its photographs: one or
    the other."""
    dataset = exp.optimize.target_dataset if exp.optimize else None
    if dataset is None:
        if exp.scene.cameras is None:
            raise where.child("scene").child("cameras").fail("missing (required)")
        return
    if exp.scene.mitsuba is not None:
        raise where.child("optimize").child("target").child("dataset").fail(
            "is not supported with an XML scene (scene.mitsuba) yet; describe the lights and the object in YAML")
    for key in ("cameras", "film"):
        if isinstance(scene_data, dict) and scene_data.get(key) is not None:
            raise where.child("scene").child(key).fail(
                "not allowed with optimize.target.dataset (the dataset's photographs give the cameras and the film)")


def check_stages(exp: Experiment):
    """The per-stage keys of ``optimize`` (``lambda``, ``downsample``) against the remesh schedule
    and the film: one value, or one per stage; each factor divides the film's width and height.
    Run at parse time and again by ``optimize``, for experiments changed in code after parsing."""
    opt, where = exp.optimize, Where(str(exp.file), "optimize")
    stages = 1 + len(opt.remesh.at)
    for name, values in (("lambda", opt.lambda_), ("downsample", opt.downsample)):
        if len(values) not in (1, stages):
            raise stage_count_error(where.child(name), stages, len(values))
    for i, k in enumerate(opt.downsample):
        key = where.child("downsample")
        if exp.scene.width % k or exp.scene.height % k:
            raise (key.child(i) if len(opt.downsample) > 1 else key).fail(
                f"{k} does not divide the film's {exp.scene.width}×{exp.scene.height} pixels")


def check_experiment(exp: Experiment):
    """Checks that need the scene's object names, views and emitters. An XML scene or a split
    OBJ object is checked once it has been read (:func:`psdr_cli.experiment.parse_experiment`)."""
    where = Where(str(exp.file), "")
    if exp.parameter and exp.parameter.object:
        names = [o.name for o in exp.scene.objects]
        if exp.parameter.object not in names:
            raise where.child("parameter").child("object").fail(
                f"unknown object '{exp.parameter.object}' (scene objects: {', '.join(names) or 'none'})")
    if exp.optimize:
        names = [o.name for o in exp.scene.objects]
        if exp.optimize.object not in names:
            raise where.child("optimize").child("object").fail(
                f"unknown object '{exp.optimize.object}' (scene objects: {', '.join(names) or 'none'})")
        bad = [v for v in exp.optimize.preview_views if v >= len(exp.scene.cameras)]
        if bad and not exp.optimize.target_images:
            raise where.child("optimize").child("preview_views").fail(
                f"view {bad[0]} does not exist (the scene has views 0..{len(exp.scene.cameras) - 1})")
        check_stages(exp)
        if exp.optimize.envmap_rotation and not any(e.type in ("envmap", "sky") for e in exp.scene.emitters):
            raise where.child("optimize").child("envmap_rotation").fail("needs an envmap or sky emitter")
        check_unknowns(exp, where.child("optimize"))
    if exp.parameter and exp.parameter.camera is not None and exp.parameter.camera >= len(exp.scene.cameras):
        raise where.child("parameter").child("camera").fail(
            f"camera {exp.parameter.camera} does not exist (the scene has cameras 0..{len(exp.scene.cameras) - 1})")
    for key, spp in (("estimator.spp", exp.estimator.spp), ("estimator.primary_spp", exp.estimator.primary_spp),
                     ("estimator.boundary_spp", exp.estimator.boundary_spp),
                     ("optimize.target.spp", exp.optimize.target_spp if exp.optimize else 0),
                     ("optimize.adjoint_spp", exp.optimize.adjoint_spp if exp.optimize else 0)):
        check_paths(spp, exp.scene.width, exp.scene.height, Where(str(exp.file), key).fail)
    if exp.parameter and exp.parameter.kind == "envmap_rotate":
        if not any(e.type in ("envmap", "sky") for e in exp.scene.emitters):
            raise where.child("parameter").child("kind").fail("'envmap_rotate' needs an envmap or sky emitter")


def check_unknowns(exp: Experiment, where: Where):
    """``optimize.envmap`` needs one ``envmap`` emitter of a YAML scene (its map is replaced) and
    excludes ``envmap_rotation``; ``optimize.material`` needs BSDF types that have the parameter."""
    o = exp.optimize
    if o.envmap is not None:
        w = where.child("envmap")
        if exp.scene.mitsuba is not None:
            raise w.fail("not available for a Mitsuba XML scene (give the scene's emitters in YAML)")
        if sum(e.type == "envmap" for e in exp.scene.emitters) != 1:
            raise w.fail("needs one emitter of type 'envmap' in scene.emitters (its map is replaced by the unknown)")
        if o.envmap_rotation:
            raise w.fail("excludes optimize.envmap_rotation (a free map holds its rotation)")
    if o.material and exp.scene.mitsuba is None:
        obj = next((x for x in exp.scene.objects if x.name == o.object), None)
        for m in o.material if obj is not None else ():
            types = MATERIAL_UNKNOWNS[m.name][1]
            if obj.bsdf.type not in types:
                raise where.child("material").child(m.name).fail(
                    f"the object's BSDF '{obj.bsdf.type}' has no {m.name} (use {' or '.join(types)})")


class UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, except that a key given twice in one mapping is an error (PyYAML
    keeps the last value silently)."""

    def construct_mapping(self, node, deep=False):
        seen = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                hash(key)
            except TypeError:
                continue  # the base class reports unhashable keys
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key '{key}' (first given on line {seen[key] + 1})", key_node.start_mark)
            seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep)


UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, UniqueKeyLoader.construct_mapping)


def read_file(path) -> Experiment:
    """Read and validate an experiment file, as :func:`parse` (its scene not yet read:
    :func:`psdr_cli.experiment.load_experiment` loads it whole)."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(path, "", "file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(path, "", f"cannot read: {exc}") from None
    try:
        data = yaml.load(text, Loader=UniqueKeyLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(path, where, f"invalid YAML: {problem}") from None
    if data is None:
        raise ConfigError(path, "", "the file is empty (expected a mapping with at least 'scene')")
    return parse(data, path)
