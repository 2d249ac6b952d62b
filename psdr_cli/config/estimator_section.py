"""``estimator``: samples per term, techniques, guides and their parameters, the engine."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from .limits import MAX_GRID_CELLS, MAX_GRID_SAMPLES, MAX_PASSES, MAX_SPP
from .values import Section, boolean, choice, integer, list_of, number
from .vocabularies import ENGINES, GUIDINGS, MITSUBA_INTEGRATORS, PRIMARY_SAMPLINGS, SAMPLINGS, TERMS


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


def term_names(value, where):
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
    est.terms = sec.get("terms", term_names, est.terms)
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
