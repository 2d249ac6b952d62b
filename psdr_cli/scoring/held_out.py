"""A reconstruction scored without a ground-truth mesh: its renders from a dataset's held-out
cameras against the photographs (``psdr evaluate`` on an experiment with
``optimize.target.dataset``). Reads the run's mesh and values and the dataset; writes one PNG
error strip per view when given a folder.

Per held-out view, with the render R and the target T (the premultiplied composite α·C when the
background is hidden, :mod:`psdr_cli.target_sources.camera_dataset`), both linear and clipped to [0, 1]:

    PSNR = 10 log10(1 / MSE(R, T))    over the whole image, and over the mask's pixels (α ≥ ½);
    SSIM = scikit-image's structural similarity (Gaussian window, σ = 1.5), its mean over the
           whole image and over the mask's pixels;
    IoU  = |{c ≥ ½} ∩ {α ≥ ½}| / |{c ≥ ½} ∪ {α ≥ ½}|, with c the rendered coverage (the share
           of a pixel's camera rays that hit the object).

Each view also gets a target | render | |error| strip (PNG, sRGB).

With ``align`` (a run that refined its training cameras), every held-out camera is first scored
as given, then aligned to the recovered scene (a pose-only fit against its photograph:
:mod:`psdr_cli.scoring.held_out_alignment`) and scored again; the strips show the aligned renders.
A run that refined its focal lengths has each held-out camera at the refined focal length of its
camera model (:mod:`psdr_cli.scoring.held_out_focal`), as given and aligned.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import mitsuba as mi
import numpy as np
from skimage.metrics import structural_similarity

from ..config.parameter import ParameterConfig
from ..config.scene_ids import emitter_id
from ..config.unknowns import MATERIAL_UNKNOWNS
from ..errors import PsdrError
from ..estimators.coverage import hit_share, object_id
from ..experiment.dataset_frame import dataset_scene, to_normalised
from ..geometry.parameters import Parameter
from ..rendering.render import render_view
from ..scene import meshes
from ..scene.build import build_scene
from ..scene.material_params import material_key, material_texture_experiment, texture_experiment, texture_lookup
from ..support import fileio
from ..target_sources.camera_dataset import dataset_views, target_image
from .held_out_alignment import align_views
from .held_out_focal import refocused_held_out
from .held_out_geometry import held_out_geometry


@dataclass
class ViewScore:
    view: str
    psnr: float
    psnr_mask: float | None
    ssim: float
    ssim_mask: float | None
    iou: float | None


@dataclass
class HeldOutResult:
    mesh: Path
    views: list = field(default_factory=list)   # of ViewScore
    strips: list = field(default_factory=list)
    aligned: list = field(default_factory=list)  # of ViewScore, from the aligned cameras (align)
    alignment: list = field(default_factory=list)  # (degrees, camera distances) each camera was moved
    focal_scales: list = field(default_factory=list)  # the refined focal scale each camera got (1: none)
    geometry: list = field(default_factory=list)   # of held_out_geometry.ViewGeometry (with a reference)

    def geometry_mean(self, key: str) -> float | None:
        values = [getattr(v, key) for v in self.geometry if getattr(v, key) is not None]
        return float(np.mean(values)) if values else None

    def mean(self, key: str, aligned: bool = False) -> float | None:
        views = self.aligned if aligned else self.views
        values = [getattr(v, key) for v in views if getattr(v, key) is not None]
        return float(np.mean(values)) if values else None


def psnr(render: np.ndarray, target: np.ndarray, where: np.ndarray | None = None) -> float:
    """10 log10(1 / MSE) of images in [0, 1], over the pixels ``where`` (all by default)."""
    err = (np.clip(render, 0, 1) - np.clip(target, 0, 1)) ** 2
    mse = float(err.mean() if where is None else err[where].mean())
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)


def ssim(render: np.ndarray, target: np.ndarray, where: np.ndarray | None = None) -> float:
    """Mean structural similarity of (H, W, 3) images in [0, 1] over the pixels ``where``."""
    _, full = structural_similarity(np.clip(render, 0, 1), np.clip(target, 0, 1), channel_axis=-1, data_range=1.0,
                                    gaussian_weights=True, sigma=1.5, use_sample_covariance=False, full=True)
    full = full.mean(axis=-1)
    return float(full.mean() if where is None else full[where].mean())


def coverage(scene, name: str, view: int, spp: int = 16, seed: int = 0) -> np.ndarray:
    """(H, W) share of each pixel's ``spp`` camera rays whose first hit is on the object ``name``."""
    width, height = scene.resolution
    share = hit_share(scene, view, spp, seed, object_id(scene, name))
    return np.asarray(share, np.float64).reshape(height, width)


def score_view(name: str, render: np.ndarray, target: np.ndarray, mask, covered) -> ViewScore:
    """The scores of one view (module docstring); ``mask`` None: no mask-restricted scores."""
    inside = None if mask is None else np.asarray(mask) >= 0.5
    iou = None
    if inside is not None:
        union = (covered >= 0.5) | inside
        iou = float(((covered >= 0.5) & inside).sum() / max(int(union.sum()), 1))
    masked = inside is not None and inside.any()
    return ViewScore(name, psnr(render, target), psnr(render, target, inside) if masked else None,
                     ssim(render, target), ssim(render, target, inside) if masked else None, iou)


def error_strip(target: np.ndarray, render: np.ndarray) -> np.ndarray:
    """target | render | |error| side by side, sRGB 8-bit."""
    error = np.abs(render - target)
    return np.round(255 * fileio.srgb(np.concatenate([target, render, error], axis=1))).astype(np.uint8)


def textured_experiment(exp, values: dict, uv):
    """``exp`` with the textures a run recovered (``values``: the albedo's ``albedo.exr``, each
    material's ``NAME.exr``) as the object's bitmaps, looked up like the run looked them up; as it
    is without them or without the mesh's texture coordinates ``uv``."""
    if uv is None:
        return exp
    albedo = values.get("albedo")
    if isinstance(albedo, str):
        exp = texture_experiment(exp, np.clip(read_texture(exp, albedo), 0.0, 1.0))
    for name in MATERIAL_UNKNOWNS:
        if isinstance(values.get(name), str):
            texels = read_texture(exp, values[name])[..., :1]
            exp = material_texture_experiment(exp, name, texels, texture_lookup(exp))
    return exp


def read_texture(exp, path) -> np.ndarray:
    """(H, W, 3) texels of a recovered texture (a linear EXR the run wrote), or one line."""
    try:
        return np.asarray(fileio.read_rgb_exr(Path(path)), np.float64)
    except Exception as exc:  # noqa: BLE001
        raise PsdrError(f"{exp.file}: cannot read the recovered texture {path}: "
                        f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None


def apply_values(scene, exp, values: dict):
    """Set the unknowns a run recovered (``optimize.json`` ``values``) in ``scene``: a constant
    albedo, constant materials (roughness, metallic, specular), the environment's rotation angle
    and a recovered environment map (``envmap``, the run's ``envmap.exr``: the texels of the
    scene's ``envmap`` emitter, whose scale and rotation stay as given). Recovered textures are
    the scene's bitmaps already (:func:`textured_experiment`)."""
    params = mi.traverse(scene.mi_scene)
    name = exp.optimize.object
    for material in MATERIAL_UNKNOWNS:
        value = values.get(material)
        if value is not None and not isinstance(value, str):
            params[material_key(name, exp.file, params, material)[0]] = mi.Float(float(np.ravel(value)[0]))
    albedo = values.get("albedo")
    if albedo is not None and not isinstance(albedo, str):
        keys = [k for k in params.keys() if k.startswith(f"{name}.bsdf.") and k.endswith(("reflectance.value",
                                                                                         "base_color.value"))]
        for k in keys[:1]:
            params[k] = mi.Color3f(*(float(a) for a in np.ravel(albedo)[:3]))
    if values.get("envmap") is not None:
        params[environment_key(exp)] = environment_texels(Path(values["envmap"]), exp)
    params.update()
    if values.get("envmap_angle") is not None:
        rotation = Parameter(scene, ParameterConfig(kind="envmap_rotate", axis=exp.optimize.envmap_axis), params)
        rotation.apply(mi.Float(float(np.ravel(values["envmap_angle"])[0])))


def environment_key(exp) -> str:
    """The Mitsuba parameter of the texels of ``exp``'s ``envmap`` emitter."""
    index = next((i for i, e in enumerate(exp.scene.emitters) if e.type == "envmap"), None)
    if index is None:
        raise PsdrError(f"{exp.file}: a recovered environment map needs an envmap emitter in scene.emitters")
    return f"{emitter_id(index)}.data"


def environment_texels(path: Path, exp):
    """Mitsuba's ``data`` tensor (H, W + 2, 3) of a lat-long EXR map: one halo column either side
    (the last and the first column), as :class:`psdr_cli.optimisation.unknowns.environment_map.Environment` writes it."""
    try:
        texels = np.asarray(fileio.read_rgb_exr(path), np.float32)
    except Exception as exc:  # noqa: BLE001
        raise PsdrError(f"{exp.file}: cannot read the recovered environment map {path}: "
                        f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    return mi.TensorXf(np.ascontiguousarray(np.concatenate([texels[:, -1:], texels, texels[:, :1]], axis=1)))


def score_mesh(exp, mesh: Path, out: Path | None = None, spp: int = 256, values: dict | None = None,
               align: bool = False, reference=None) -> HeldOutResult:
    """Render ``mesh`` (in the dataset's coordinates) with the recovered ``values``
    (:func:`apply_values`) from every held-out camera of ``exp``'s dataset and score it against
    the photographs; strips go to ``out`` when given; with ``align``, scored again from the
    aligned cameras (module docstring); with a ``reference`` (V, F), depth and normals against it
    (:mod:`psdr_cli.scoring.held_out_geometry`, from the aligned cameras when aligned)."""
    values = values or {}
    test, scales = refocused_held_out(dataset_scene(exp, split="test"), values.get("cameras"))
    views = dataset_views(test)
    V, F, uv = meshes.read_mesh_file_uv(mesh)
    plain, test = test, textured_experiment(test, values, uv)
    shape = (to_normalised(V, test.optimize.target_dataset.frame), F) + ((uv,) if uv is not None else ())
    scene = build_scene(test, objects={test.optimize.object: shape})
    apply_values(scene, test, values)
    result = HeldOutResult(Path(mesh), focal_scales=scales)
    if out is not None:
        fileio.writable_folder(out)
    targets = [target_image(view, test.scene.hide_background) for view in views]
    if not views:
        raise PsdrError(f"{exp.file}: optimize.target.dataset: no held-out views to score")
    result.views, renders = score_views(scene, test, views, targets, spp)
    if align:
        cams = align_views(scene, test, targets)
        result.aligned, renders = score_views(scene, test, views, targets, spp)
        result.alignment = list(zip(*cams.errors()))
    if reference is not None:
        result.geometry = held_out_geometry(scene, plain, views, reference)
    if out is not None:
        for v, (target, render) in enumerate(zip(targets, renders)):
            path = out / f"{Path(mesh).stem}_view_{v:03d}.png"
            fileio.write_png(path, error_strip(target, render))
            result.strips.append(path)
    return result


def score_views(scene, test, views, targets: list, spp: int) -> tuple:
    """(:class:`ViewScore` of each held-out view rendered from the scene's cameras as they are,
    the renders)."""
    scores, renders = [], []
    for v, (view, target) in enumerate(zip(views, targets)):
        render = np.asarray(render_view(scene, v, spp, seed=test.seed), np.float64)
        scores.append(score_view(view.name, render, target, view.mask, coverage(scene, test.optimize.object, v)))
        renders.append(render)
    return scores, renders
