"""A reconstruction scored under other light (``psdr evaluate cfg.yaml --relight DATASET --envmap
MAP.exr``), as Stanford-ORB scores inverse rendering: the recovered object (its mesh, albedo and
material values or textures; not its recovered light) is rendered under the lat-long map MAP
(times ``scale``) from every camera of DATASET (photographs of the object under that light, in the
training capture's world frame, any format psdr reads) and compared with the photographs.
Reads the run, the dataset and the map; writes one PNG error strip per view when given a folder.

Light × albedo is ambiguous, so before scoring each view's render R is given the per-channel
least-squares scale against its photograph T over the mask's pixels M (α ≥ ½):

    s_c = Σ_M R_c T_c / Σ_M R_c²,   R' = s ⊙ R.

Then, inside the mask:

    PSNR-H = 10 log10(max_M(T)² / MSE(R', T))   on linear values (high dynamic range when the
                                                 photographs are EXR; their peak sets the range),
    PSNR-L = 10 log10(1 / MSE(srgb(R'), srgb(T))) on sRGB values clipped to [0, 1],
    SSIM   = scikit-image's SSIM of the sRGB images (σ = 1.5), its mean over the mask.

A target | render | error strip per view (sRGB) goes to ``<run>/relight/``, with relight.json.
Before anything is scored, a relight dataset whose masks the object misses (mean mask IoU below
:data:`MIN_IOU`: another world frame) and a map that is not a finite, non-negative lat-long EXR
(width = 2 × height) are refused in one line.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..config.dataset import DatasetConfig
from ..config.emitters import EmitterConfig
from ..errors import PsdrError
from ..scoring.held_out import apply_values, coverage, error_strip, ssim, textured_experiment
from ..experiment.dataset_frame import dataset_frames, dataset_scene, to_normalised, world_up
from ..rendering.render import render_view
from ..scene import meshes
from ..scene.build import build_scene
from ..support import fileio
from ..target_sources.camera_dataset import dataset_views, target_image

#: Mean mask IoU of the relit object below which the relight dataset is taken to be in another
#: world frame than the training capture.
MIN_IOU = 0.3

#: Recovered values that belong to the training light, not the object (not applied when relit).
LIGHT_VALUES = ("envmap", "envmap_angle")


@dataclass
class RelitView:
    view: str
    psnr_h: float
    psnr_l: float
    ssim: float
    iou: float
    scale: tuple


@dataclass
class RelightResult:
    mesh: Path
    dataset: Path
    envmap: Path
    views: list = field(default_factory=list)    # of RelitView
    strips: list = field(default_factory=list)

    def mean(self, key: str) -> float:
        return float(np.mean([getattr(v, key) for v in self.views]))


def check_latlong(path: Path) -> np.ndarray:
    """The texels (H, W, 3) of a lat-long EXR environment map, or one line saying why not."""
    path = Path(path)
    if path.suffix.lower() != ".exr" or not path.is_file():
        raise PsdrError(f"{path}: --envmap: expected an existing lat-long EXR environment map")
    try:
        texels = np.asarray(fileio.read_rgb_exr(path), np.float64)
    except Exception as exc:  # noqa: BLE001 - a damaged or non-RGB EXR
        raise PsdrError(f"{path}: --envmap: cannot read it as an RGB EXR "
                        f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    height, width = texels.shape[:2]
    if width != 2 * height:
        raise PsdrError(f"{path}: --envmap: {width}×{height} is not a lat-long map (expected width = 2 × height)")
    if not np.isfinite(texels).all() or texels.min() < 0:
        raise PsdrError(f"{path}: --envmap: expected finite, non-negative radiance")
    return texels


def relight_experiment(exp, dataset: Path, envmap: Path, scale: float):
    """``exp`` with its dataset replaced by the relight ``dataset`` (every frame scored, the
    training capture's up axis kept) and its light by the one ``envmap`` emitter (``scale``)."""
    train = exp.optimize.target_dataset
    up = world_up(dataset_frames(train, "train")[0], train.up)
    relit = DatasetConfig(path=Path(dataset), key="--relight", up=up)
    emitter = EmitterConfig(type="envmap", key="--envmap", file=Path(envmap), scale=scale)
    return replace(exp, scene=replace(exp.scene, emitters=[emitter]),
                   optimize=replace(exp.optimize, target_dataset=relit))


def channel_scale(render: np.ndarray, target: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """s_c = Σ R_c T_c / Σ R_c² over the pixels ``inside`` (1 for a channel the render leaves black)."""
    R, T = render[inside], target[inside]
    power = (R * R).sum(0)
    return np.where(power > 0, (R * T).sum(0) / np.maximum(power, 1e-30), 1.0)


def score_relit(name: str, render: np.ndarray, target: np.ndarray, mask, covered) -> tuple:
    """(:class:`RelitView`, the scaled render) of one view (module docstring)."""
    inside = (np.ones(target.shape[:2]) if mask is None else np.asarray(mask)) >= 0.5
    scale = channel_scale(render, target, inside)
    scaled = render * scale
    mse = float(((scaled - target) ** 2)[inside].mean())
    peak = float(target[inside].max()) if inside.any() else 1.0
    srgb_r, srgb_t = fileio.srgb(scaled), fileio.srgb(target)
    mse_l = float(((srgb_r - srgb_t) ** 2)[inside].mean())
    union = (covered >= 0.5) | inside
    iou = float(((covered >= 0.5) & inside).sum() / max(int(union.sum()), 1))
    to_db = lambda peak2, err: float("inf") if err == 0 else 10 * np.log10(peak2 / err)  # noqa: E731
    return RelitView(name, to_db(peak * peak, mse), to_db(1.0, mse_l), ssim(srgb_r, srgb_t, inside), iou,
                     tuple(float(s) for s in scale)), scaled


def relight_mesh(exp, mesh: Path, dataset: Path, envmap: Path, *, scale: float = 1.0, values: dict | None = None,
                 out: Path | None = None, spp: int = 256) -> RelightResult:
    """``mesh`` (the dataset's coordinates) with the recovered ``values`` relit by ``envmap`` from
    every camera of ``dataset`` and scored (module docstring); strips go to ``out``."""
    check_latlong(envmap)
    relit = dataset_scene(relight_experiment(exp, dataset, envmap, scale), split="all")
    views = dataset_views(relit)
    values = {k: v for k, v in (values or {}).items() if k not in LIGHT_VALUES}
    V, F, uv = meshes.read_mesh_file_uv(mesh)
    relit = textured_experiment(relit, values, uv)
    shape = (to_normalised(V, relit.optimize.target_dataset.frame), F) + ((uv,) if uv is not None else ())
    scene = build_scene(relit, objects={relit.optimize.object: shape})
    apply_values(scene, relit, values)
    result = RelightResult(Path(mesh), Path(dataset), Path(envmap))
    images = []
    for v, view in enumerate(views):
        target = target_image(view, relit.scene.hide_background)
        render = np.asarray(render_view(scene, v, spp, seed=relit.seed), np.float64)
        score, scaled = score_relit(view.name, render, target, view.mask, coverage(scene, relit.optimize.object, v))
        result.views.append(score)
        images.append((target, scaled))
    if result.mean("iou") < MIN_IOU:
        raise PsdrError(f"{dataset}: --relight: the object misses the photographs' masks (mean IoU "
                        f"{result.mean('iou'):.2f}): is this dataset in the training capture's world frame?")
    if out is not None:
        fileio.writable_folder(out)
        for v, (target, scaled) in enumerate(images):
            path = out / f"{Path(mesh).stem}_view_{v:03d}.png"
            fileio.write_png(path, error_strip(target, scaled))
            result.strips.append(path)
    return result
