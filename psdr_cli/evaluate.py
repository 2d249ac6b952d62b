"""Shape error (``psdr evaluate``): symmetric Chamfer and Hausdorff distances to a reference.

Both meshes are normalised with the *reference's* bounding box (centre at the origin, longest
side 1), N points are drawn on each surface by area with a fixed seed, and with
d(p, Q) = min_q |p − q| (nearest sampled point, scipy's cKDTree):

    Chamfer-L1  = ½ (mean_{p∈P} d(p, Q) + mean_{q∈Q} d(q, P)),
    Chamfer-L2² = ½ (mean_{p∈P} d(p, Q)² + mean_{q∈Q} d(q, P)²),
    Hausdorff   = max(max_P d(p, Q), max_Q d(q, P)).

Point sampling puts a noise floor under these numbers: two independent samplings of the same
surface are on average ~0.5/√N·(area)^½ apart; :func:`noise_floor` measures it.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import PsdrError


@dataclass
class Distance:
    chamfer_l1: float
    chamfer_l2: float
    hausdorff: float


def load(path: Path):
    """(V, F) of a PLY/OBJ mesh with one-line errors for missing, unreadable or empty files."""
    from .meshes import read_mesh_file
    path = Path(path)
    if not path.exists():
        raise PsdrError(f"{path}: file not found")
    try:
        V, F = read_mesh_file(path)
    except Exception as exc:  # noqa: BLE001 - any parser failure
        raise PsdrError(f"{path}: cannot read mesh ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    if len(V) == 0 or len(F) == 0:
        raise PsdrError(f"{path}: mesh is empty ({len(V)} vertices, {len(F)} triangles)")
    return V, F


def normalisation(V):
    """(centre, scale) mapping the bounding box of V to a box with longest side 1 at the origin."""
    lo, hi = V.min(0), V.max(0)
    return (lo + hi) / 2, 1.0 / max(float((hi - lo).max()), 1e-30)


def surface_points(V, F, n: int, seed: int):
    """n points uniformly distributed by area on the triangles (V, F)."""
    from .meshes import face_areas
    rng = np.random.default_rng(seed)
    area = face_areas(V, F)
    if not area.sum() > 0:
        raise PsdrError("mesh has zero surface area")
    tri = rng.choice(len(F), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    a, b, c = V[F[tri, 0]], V[F[tri, 1]], V[F[tri, 2]]
    return (1 - s)[:, None] * a + (s * (1 - r2))[:, None] * b + (s * r2)[:, None] * c


def distance(mesh, reference, samples: int = 100_000, seed: int = 0) -> Distance:
    """Chamfer (L1, squared L2) and Hausdorff distance of ``mesh`` to ``reference`` (each (V, F)),
    both normalised with the reference's bounding box."""
    from scipy.spatial import cKDTree
    centre, scale = normalisation(reference[0])
    P = surface_points((mesh[0] - centre) * scale, mesh[1], samples, seed)
    Q = surface_points((reference[0] - centre) * scale, reference[1], samples, seed + 1)
    dp = cKDTree(Q).query(P, workers=-1)[0]
    dq = cKDTree(P).query(Q, workers=-1)[0]
    return Distance(0.5 * (dp.mean() + dq.mean()), 0.5 * ((dp ** 2).mean() + (dq ** 2).mean()),
                    float(max(dp.max(), dq.max())))


def noise_floor(reference, samples: int = 100_000, seed: int = 0) -> Distance:
    """The distance of the reference to itself with independent samplings."""
    return distance(reference, reference, samples, seed + 1000)


def run_checkpoints(folder: Path):
    """[(iteration, path)] of a ``psdr optimize`` run folder (initial shape, checkpoints, final)."""
    folder = Path(folder)
    found = sorted((int(p.stem.split("_")[1]), p) for p in (folder / "checkpoints").glob("iter_*.ply"))
    if not found:
        raise PsdrError(f"{folder}: no checkpoints (expected checkpoints/iter_NNNN.ply from `psdr optimize`)")
    return found


def run_seconds(folder: Path) -> dict:
    """{iteration: optimisation seconds so far} from the run's log.csv (iteration i ends at i+1)."""
    log = Path(folder) / "log.csv"
    if not log.exists():
        return {}
    with open(log, newline="") as f:
        return {int(r["iteration"]) + 1: float(r["seconds_total"]) for r in csv.DictReader(f)}


def run_summary(folder: Path) -> dict:
    """Per-iteration time split and guide memory of a ``psdr optimize`` run (the columns of the
    paper's Table 2), from its log.csv and optimize.json:

        guiding / rendering / post-processing seconds = mean over the logged iterations,
        guide memory = the largest guide set built (bytes)."""
    import json
    folder = Path(folder)
    log = folder / "log.csv"
    if not log.exists():
        raise PsdrError(f"{folder}: no log.csv (expected a `psdr optimize` run folder)")
    with open(log, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise PsdrError(f"{log}: no iterations logged")
    mean = lambda key: float(np.mean([float(r[key]) for r in rows]))  # noqa: E731
    try:
        info = json.loads((folder / "optimize.json").read_text())
    except (OSError, ValueError):
        info = {}
    if info.get("iterations") != len(rows):
        raise PsdrError(f"{folder}: the run is unfinished ({len(rows)} iterations logged, no final result); "
                        f"finish it with `psdr optimize --resume`")
    return {"iterations": len(rows), "seconds": float(rows[-1]["seconds_total"]),
            "seconds_guiding": mean("seconds_guiding"), "seconds_rendering": mean("seconds_rendering"),
            "seconds_post": mean("seconds_post"), "vertices": int(rows[-1]["vertices"]),
            "guide_bytes": max(int(r.get("guide_bytes") or 0) for r in rows), "views": info.get("views")}


def mesh_view(V, F, reference_V, size: int = 160, spp: int = 64, direction=(0.55, -1.0, 0.45)) -> np.ndarray:
    """A neutral picture of a mesh for side-by-side comparisons (H, W, 3 in [0, 1] sRGB): grey
    two-sided diffuse under a constant sky and a directional key light, framed on the *reference's*
    bounding sphere so that all meshes of one comparison share the camera."""
    import mitsuba as mi
    from .io import srgb
    from .scene import look_at, mitsuba_mesh
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
    return srgb(np.asarray(mi.render(scene, spp=spp), np.float64)[..., :3])
