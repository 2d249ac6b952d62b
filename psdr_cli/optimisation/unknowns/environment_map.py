"""``optimize.envmap``: the lat-long map of the scene's ``envmap`` emitter as the unknown x (H, W, 3)
of log-radiance (Adam entry ``envmap``, saved value ``envmap_log``); the emitter's texels are
exp(x) (:class:`Environment`), its mean radiance optionally held (``optimize.envmap.mean``) and its
smoothness a prior. Owns that emitter's texels; its checkpoint file is ``envmap.exr``, the map
as the emitter uses it (before its scale), and ``psdr export`` writes exp(x)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ...config.scene_ids import emitter_id
from ...run_folder.checkpoints import Picture
from ...scene.build import exr_texels
from ...support.jitarray import jit_array
from .unknown import Saved, Start, Unknown, detached


class EnvironmentMap(Unknown):
    """The environment map being recovered (module docstring)."""
    name = "environment_map"

    @staticmethod
    def wanted(cfg) -> bool:
        return cfg.envmap is not None

    def __init__(self, start: Start):
        super().__init__(start)
        cfg = start.cfg
        self.map = Environment(cfg, start.source.scene.emitters, start.params, start.values.get("envmap_log"))
        self.smoothness = cfg.envmap.smoothness
        start.opt["envmap"] = self.map.initial
        start.opt.set_learning_rate({"envmap": cfg.envmap.learning_rate})

    def entries(self) -> dict:
        return {"envmap": (self.start.opt, "envmap")}

    def scene_values(self) -> dict:
        return {self.map.key: self.map.texels(self.start.opt["envmap"])}

    def write_saved(self, saved: Saved):
        if "envmap_log" in saved.values:
            self.start.params[self.map.key] = self.map.texels(jit_array(mi.TensorXf, saved.values["envmap_log"]))

    def step(self, at):
        """The mean radiance held at the initial map's (``optimize.envmap.mean``; Adam's moments kept)."""
        if self.map.fixed_mean:
            self.start.opt["envmap"] = self.map.normalised(self.start.opt["envmap"])

    def prior(self):
        """smoothness · the log-radiance's roughness (:meth:`Environment.roughness`), or None."""
        if self.smoothness > 0:
            return self.smoothness * self.map.roughness(self.start.opt["envmap"])
        return None

    def values(self) -> dict:
        return {"envmap_log": np.asarray(self.start.opt["envmap"], np.float64)}

    def radiance(self) -> np.ndarray:
        """exp(x) as (H, W, 3) numpy: the map as the emitter uses it (before its scale)."""
        return self.map.radiance(self.start.opt["envmap"])

    def checkpoint_files(self, files, iteration: int) -> list:
        return [Picture(files.envmap, self.radiance(), png=False)]

    def summary(self, files) -> dict:
        return {"envmap": str(files.envmap)}

    def detach(self):
        detached(self.start.params, self.map.key)

    @staticmethod
    def export(asset, state, exp, where):
        """The recovered map exp(x) as the asset's environment."""
        if state.values.get("envmap_log") is not None:
            asset.environment = np.exp(np.asarray(state.values["envmap_log"], np.float64))
            asset.record["environment"] = "the recovered optimize.envmap (use it with the emitter's scale and rotate_deg)"


class Environment:
    """``optimize.envmap``: the lat-long map of the scene's ``envmap`` emitter as the unknown
    x (H, W, 3) of log-radiance; the emitter's texels are exp(x) (its ``scale`` and rotation as
    given). Mitsuba's ``data`` is (H, W + 2, 3): one halo column either side, refreshed by the
    emitter from the real columns (each halo's derivative routed onto its source column)."""

    def __init__(self, cfg, emitters: list, params, saved=None):
        """``cfg``: the ``optimize`` section; ``emitters``: the scene's; ``saved``: the saved
        log-radiance, or None for the initial map."""
        optimize, cfg = cfg, cfg.envmap
        index = next(i for i, e in enumerate(emitters) if e.type == "envmap")
        self.key = f"{emitter_id(index)}.data"
        self.W, self.H = cfg.resolution
        scene_map = np.asarray(params[self.key], np.float64)[:, 1:-1]  # the map the scene was built with
        self.weights = solid_angle_weights(self.H, self.W)
        if cfg.init_file is not None:
            start = latlong_resample(np.asarray(exr_texels(cfg.init_file), np.float64)[..., :3], self.W, self.H)
        elif cfg.init is not None:
            start = np.broadcast_to(np.asarray(cfg.init, np.float64), (self.H, self.W, 3))
        else:
            w = solid_angle_weights(*scene_map.shape[:2])
            start = np.broadcast_to((scene_map * w[..., None]).sum((0, 1)) / w.sum(), (self.H, self.W, 3))
        start = np.maximum(start, 1e-4 * max(float(start.max()), 1e-30))  # log-radiance needs > 0
        self.mean = float((start * self.weights[..., None]).sum() / (3 * self.weights.sum()))
        self.fixed_mean = cfg.mean == "fixed" or (cfg.mean == "auto" and optimize.albedo)
        self.initial = jit_array(mi.TensorXf, np.log(start) if saved is None else saved)
        cols = np.concatenate([[self.W - 1], np.arange(self.W), [0]])
        idx = ((np.arange(self.H)[:, None] * self.W + cols[None, :])[..., None] * 3 + np.arange(3)).ravel()
        self.halo = jit_array(mi.UInt32, idx)
        self.w = jit_array(mi.Float, np.repeat(self.weights.ravel() / (3 * self.weights.sum()), 3))
        right = (np.arange(self.W) + 1) % self.W
        a = np.arange(self.H * self.W).reshape(self.H, self.W)
        pairs = np.concatenate([np.stack([a.ravel(), a[:, right].ravel()], 1),
                                np.stack([a[:-1].ravel(), a[1:].ravel()], 1)])
        pairs = (pairs[:, :, None] * 3 + np.arange(3)).transpose(0, 2, 1).reshape(-1, 2)
        self.pairs = (jit_array(mi.UInt32, pairs[:, 0]), jit_array(mi.UInt32, pairs[:, 1]))

    def texels(self, x):
        """Mitsuba's ``data`` tensor (H, W + 2, 3) of the log-radiance x (AD-attached)."""
        flat = dr.gather(mi.Float, dr.exp(x.array), self.halo)
        return mi.TensorXf(flat, (self.H, self.W + 2, 3))

    def radiance(self, x) -> np.ndarray:
        """exp(x) as (H, W, 3) numpy."""
        return np.exp(np.asarray(dr.detach(x), np.float64))

    def normalised(self, x):
        """x shifted so that the solid-angle mean of exp(x) is the initial map's."""
        mean = dr.sum(self.w * dr.exp(dr.detach(x.array)))
        return mi.TensorXf(dr.detach(x.array) - dr.log(mean / self.mean), x.shape)

    def roughness(self, x):
        """Mean squared difference of the log-radiance between neighbouring texels (longitude
        wraps around, latitude does not): the quadratic form of the grid's graph Laplacian."""
        d = dr.gather(mi.Float, x.array, self.pairs[0]) - dr.gather(mi.Float, x.array, self.pairs[1])
        return dr.mean(d * d)


def solid_angle_weights(H: int, W: int) -> np.ndarray:
    """(H, W) solid angles (up to a factor) of the texels of a lat-long map: sin θ of each row."""
    theta = (np.arange(H) + 0.5) / H * np.pi
    return np.broadcast_to(np.sin(theta)[:, None], (H, W)).copy()


def latlong_resample(image, W: int, H: int) -> np.ndarray:
    """A lat-long map (h, w, 3) resampled to (H, W, 3): bilinear at texel centres, longitude
    wrapping around, latitude clamped (the same map when the size is the same)."""
    h, w = image.shape[:2]
    if (h, w) == (H, W):
        return np.asarray(image, np.float64)
    x = (np.arange(W) + 0.5) / W * w - 0.5
    y = np.clip((np.arange(H) + 0.5) / H * h - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[None, :, None], (y - y0)[:, None, None]
    y1 = np.minimum(y0 + 1, h - 1)
    xa, xb = x0 % w, (x0 + 1) % w
    row = lambda r: image[r][:, xa] * (1 - fx) + image[r][:, xb] * fx  # noqa: E731
    return row(y0) * (1 - fy) + row(y1) * fy


UNKNOWN = EnvironmentMap
