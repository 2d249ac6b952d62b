"""``optimize``: the object to reconstruct, its targets and initial shape, the remesh schedule,
the step sizes, the extra unknowns and the run's variants."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from .dataset import DatasetConfig, parse_dataset
from .limits import MAX_FILM, MAX_ITERATIONS, MAX_SPP, MAX_VERTICES
from .objects import MeshSpec, TransformConfig, parse_mesh, parse_transform
from .unknowns import CamerasUnknown, EnvmapUnknown, parse_cameras, parse_envmap_unknown, parse_material, texture_size
from .values import Parser, Section, boolean, choice, integer, list_of, number, per_stage, reflectance, string, vector
from .variants_section import run_variant_parser, unique_labels
from .vocabularies import REMESH_METHODS


@dataclass
class RemeshConfig:
    method: str = "instant"          # instant (field-aligned) | isotropic | none
    initial: int = 1500              # vertices of the remeshed initial shape
    at: tuple = ()                   # iterations at which to remesh again
    vertices: tuple = ()             # vertex budget at each of those iterations


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
    freeze: bool = True                    # record and replay the adjoint render and the recorded parts (frozen_batch.py)
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
    cameras: CamerasUnknown = field(default_factory=CamerasUnknown)  # pose refinement of the views
    seconds: float | None = None           # wall-clock budget of the optimisation (equal-time runs)
    outlier_clip: str | float = "auto"     # each gradient scaled to at most c times its running norm (outlier_clip.py)
    variants: tuple = ()                   # of Variant: one run folder each, <output>/<name>/<label>
    target_seed: int | None = None         # not a YAML key: a variant's targets use its base experiment's seed
    target_keys: dict = field(default_factory=dict)  # optimize.target keys of other sources: {key: parsed value}


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


def _outlier_clip(value, where):
    """``auto``, ``off`` or a factor c ≥ 1 (each gradient is scaled to at most c times its running norm)."""
    if value in ("auto", "off"):
        return value
    if isinstance(value, str):
        raise where.fail(f"expected auto, off or a number >= 1, got '{value}'")
    return number(minimum=1)(value, where)


def needs_uv(opt: OptimizeConfig) -> bool:
    """Whether the shape being optimised needs texture coordinates: a texture is recovered
    (``optimize.albedo.texture`` or ``optimize.material.NAME.texture``)."""
    return bool((opt.albedo and opt.albedo_texture is not None) or any(m.texture is not None for m in opt.material))


def unwrap_size(opt: OptimizeConfig) -> tuple:
    """(W, H) a UV atlas is laid out for: the largest texture being recovered (:func:`needs_uv`)."""
    sizes = ([opt.albedo_texture] if opt.albedo and opt.albedo_texture is not None else []) + \
        [m.texture for m in opt.material if m.texture is not None]
    return max(sizes, key=lambda s: s[0] * s[1])


def parse_optimize(base: Path) -> Parser:
    """The ``optimize`` section; paths relative to ``base`` (the experiment file's folder)."""
    def parse(value, where) -> OptimizeConfig:
        sec = Section(value, where)
        o = OptimizeConfig(object=sec.get("object", string, None))
        if sec.has("target"):
            read_target(Section(sec.get("target", lambda v, _: v), where.child("target")), o, base)
        if sec.has("init"):
            read_init(Section(sec.get("init", lambda v, _: v), where.child("init")), o, base)
        if o.object is None:
            raise where.child("object").fail("missing (the object to reconstruct; or target: {object: NAME})")
        read_schedule(sec, o)
        if sec.has("albedo"):
            read_albedo(Section(sec.get("albedo", lambda v, _: v), where.child("albedo")), o)
        if sec.has("envmap_rotation"):
            read_envmap_rotation(Section(sec.get("envmap_rotation", lambda v, _: v), where.child("envmap_rotation")), o)
        o.envmap = sec.get("envmap", parse_envmap_unknown(base), None)
        o.material = sec.get("material", parse_material, ())
        o.cameras = sec.get("cameras", parse_cameras, o.cameras)
        o.seconds = sec.get("seconds", number(positive=True), None)
        o.outlier_clip = sec.get("outlier_clip", _outlier_clip, o.outlier_clip)
        if sec.has("variants"):
            o.variants = tuple(sec.get("variants", list_of(run_variant_parser(1 + len(o.remesh.at)), min_len=1)))
            unique_labels(o.variants, where)
        sec.done()
        return o
    return parse


#: The ``optimize.target`` keys of target sources other than ``images``, ``mesh`` and
#: ``dataset`` (which the layers below the sources read too): {key: parser factory(base folder)},
#: each registered by its source (:attr:`psdr_cli.target_sources.source.TargetSource.keys`) when
#: :mod:`psdr_cli.target_sources.registry` is imported, as importing :mod:`psdr_cli` does (this
#: package reads no module above it). The value parsed goes to ``OptimizeConfig.target_keys``.
SOURCE_KEYS: dict = {}


def register_target_keys(keys: dict):
    """Accept ``optimize.target.KEY`` for each ``{KEY: parser factory}`` of a target source."""
    clash = [k for k in keys if k in ("object", "spp", "images", "mesh", "dataset")]
    if clash:
        raise ValueError(f"optimize.target.{clash[0]} is psdr's own key")
    SOURCE_KEYS.update(keys)


def read_target(t: Section, o: OptimizeConfig, base: Path):
    """``optimize.target: {object | images | mesh | dataset | a source's own key, spp}`` into
    ``o``: one source of target images (``target: {object: NAME}`` is an alias of
    ``optimize.object``)."""
    given = [k for k in ("images", "mesh", "dataset", *SOURCE_KEYS) if t.has(k)]
    if len(given) > 1:
        names = ("images", "mesh", "dataset", *SOURCE_KEYS)
        raise t.where.fail(f"give one of {', '.join(repr(k) for k in names[:-1])} and {names[-1]!r}, "
                           f"not {' and '.join(given)}")
    if t.has("object"):
        name = t.get("object", string)
        if o.object is not None and o.object != name:
            raise t.where.child("object").fail(f"'{name}' contradicts optimize.object '{o.object}' (give one of them)")
        o.object = name
    o.target_images = t.get("images", string, None)
    if o.target_images is not None and not Path(o.target_images).is_absolute():
        o.target_images = str(base / o.target_images)
    o.target_mesh = t.get("mesh", parse_mesh(base), None)
    o.target_dataset = t.get("dataset", parse_dataset(base), None)
    o.target_keys = {k: t.get(k, parser(base)) for k, parser in SOURCE_KEYS.items() if t.has(k)}
    o.target_spp = t.get("spp", integer(1, MAX_SPP), o.target_spp)
    t.done()


def read_init(i: Section, o: OptimizeConfig, base: Path):
    """``optimize.init: {mesh, transform}`` into ``o`` (``mesh: null``: the default sphere)."""
    o.init = i.get("mesh", parse_mesh(base), None)
    o.init_transform = i.get("transform", parse_transform, TransformConfig())
    if o.init is None and i.has("transform"):
        raise i.where.child("transform").fail(
            "needs init.mesh (the default initial shape is a sphere around the target's bounding box)")
    i.done()


def read_schedule(sec: Section, o: OptimizeConfig):
    """The remesh schedule, the iterations and batches, the step sizes and λ (one or one per
    stage), the guide, adjoint and checkpoint cadence, and the preview views, into ``o``."""
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
    o.freeze = sec.get("freeze", boolean, o.freeze)
    o.preview_views = tuple(sec.get("preview_views", list_of(integer(0), min_len=1), list(o.preview_views)))


def read_albedo(a: Section, o: OptimizeConfig):
    """``optimize.albedo: {init, learning_rate, texture}`` into ``o``: the albedo as an unknown."""
    o.albedo = True
    o.albedo_init = a.get("init", reflectance, None)
    o.albedo_learning_rate = a.get("learning_rate", number(positive=True), o.albedo_learning_rate)
    o.albedo_texture = a.get("texture", texture_size, None)
    a.done()


def read_envmap_rotation(e: Section, o: OptimizeConfig):
    """``optimize.envmap_rotation: {axis, init_deg, learning_rate}`` into ``o``."""
    o.envmap_rotation = True
    o.envmap_axis = e.get("axis", vector(3, nonzero=True), o.envmap_axis)
    o.envmap_init_deg = e.get("init_deg", number(), o.envmap_init_deg)
    o.envmap_learning_rate = e.get("learning_rate", number(positive=True), o.envmap_learning_rate)
    e.done()
