"""The target source ``dataset`` (``optimize.target.dataset``): the photographs of the
views the experiment's cameras are (:mod:`psdr_cli.experiment.dataset_frame`), decoded to linear RGB at the
film's size, and the initial shape: the masks' visual hull, or a sphere without masks.

With the background hidden (masked photographs), a target is the premultiplied composite
T = α·C of the straight colour C and the mask α, the same composite the renderer then draws
(colour × coverage, :func:`psdr_cli.estimators.interior.radiance`): silhouette pixels are
compared as partial coverage, neither dark halos nor ignored, and a real background never pulls
on the shape. With a visible background the photograph is compared as it is.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..datasets.masks import check_masks
from ..datasets.views import load_views
from ..errors import PsdrError
from ..experiment.dataset_frame import dataset_frames, to_normalised
from ..scene import meshes
from .source import TargetInputs, TargetMasks, TargetSource
from .visual_hull import visual_hull


def undistortion_cache(exp):
    """Where a run keeps its undistorted photographs: ``targets/undistorted/`` in its folder
    (files named by a hash of their source and intrinsics, so any run may reuse them; the targets
    folder survives a fresh start)."""
    return exp.run_dir / "targets" / "undistorted"


def dataset_views(exp):
    """The views of the experiment's cameras (``target_dataset.split``), decoded at the film's size,
    with their cameras moved into the normalised frame; masks that cannot be right are refused
    (:mod:`psdr_cli.datasets.masks`)."""
    dataset = exp.optimize.target_dataset
    _, chosen = dataset_frames(dataset, dataset.split)
    views = load_views(chosen, downsample=dataset.downsample, linear=dataset.linear, cache=undistortion_cache(exp),
                       key=f"{dataset.key}.downsample")
    check_masks(views)
    for view in views:
        if view.image.shape[:2] != (exp.scene.height, exp.scene.width):
            raise PsdrError(f"{view.name}: the photograph is {view.image.shape[1]}×{view.image.shape[0]} pixels "
                            f"after downsampling, the other views {exp.scene.width}×{exp.scene.height}")
    return [normalised_view(v, dataset.frame) for v in views]


def normalised_view(view, frame):
    """A view with its camera position in the normalised frame (rotation and intrinsics kept)."""
    M = np.array(view.cam_to_world, np.float64)
    M[:3, 3] = to_normalised(M[:3, 3], frame)
    return replace(view, cam_to_world=M)


def target_image(view, hidden: bool) -> np.ndarray:
    """The image an optimisation fits for one view: α·C with the background hidden (a view without
    a mask counts as covered everywhere), the photograph C otherwise."""
    image = np.asarray(view.image, np.float64)
    if hidden and view.mask is not None:
        image = image * np.asarray(view.mask, np.float64)[..., None]
    if not np.isfinite(image).all():
        raise PsdrError(f"{view.name}: the decoded photograph has non-finite values")
    return image


def dataset_targets(exp):
    """(target images, views) of the experiment's cameras. With the background hidden, a mask that
    covers the whole of every photograph (an opaque alpha channel) is refused: it would fit the
    photographs' backgrounds as part of the object."""
    views = dataset_views(exp)
    if exp.scene.hide_background and views and all(v.mask is not None and v.mask.min() >= 0.999 for v in views):
        raise PsdrError(f"{exp.optimize.target_dataset.path}: every photograph's mask (alpha) is opaque everywhere: "
                        f"not a mask of the object; set optimize.target.dataset.background: visible")
    return [target_image(v, exp.scene.hide_background) for v in views], views


def l1_weight(view, mask_file: bool) -> np.ndarray:
    """The weight of each pixel of a view in the L1 loss: with a separate mask file the colour of
    a pixel the mask covers only partly (0 < α < 1) mixes the object with the real background,
    which no render reproduces: weight 0 there (its silhouette is the silhouette loss's), 1
    elsewhere. With the image's own alpha (straight colour) every pixel counts."""
    if not mask_file or view.mask is None:
        return np.ones(view.image.shape[:2])
    return ((view.mask <= 0.01) | (view.mask >= 0.99)).astype(np.float64)


def dataset_masks(exp, views):
    """The :class:`~.source.TargetMasks` of the experiment's views when every one has a
    mask, else None."""
    if not views or any(v.mask is None for v in views):
        return None
    _, frames = dataset_frames(exp.optimize.target_dataset, exp.optimize.target_dataset.split)
    weights = [l1_weight(v, f.mask is not None) for v, f in zip(views, frames)]
    return TargetMasks([v.mask for v in views], weights if any(f.mask is not None for f in frames) else None)


def dataset_initial_shape(exp, views):
    """(V, F) of the initial shape in the normalised frame: the masks' visual hull when every
    view has a mask, else a sphere of radius ½ at the cameras' look-at point (the origin)."""
    if views and all(v.mask is not None for v in views):
        try:
            return visual_hull(views)
        except PsdrError as exc:
            raise PsdrError(f"{exp.optimize.target_dataset.path}: {exc}") from None
    return meshes.sphere(radius=0.5, subdivisions=3)


def read_dataset(exp) -> TargetInputs:
    """The photographs of the experiment's views as targets, with their masks (:func:`dataset_masks`)."""
    images, views = dataset_targets(exp)
    return TargetInputs(images, None, None, masks=dataset_masks(exp, views), views=views)


def dataset_initial(exp, inputs: TargetInputs):
    """The visual hull of the views (:func:`dataset_initial_shape`, no UVs) unless ``init`` is given."""
    return None if exp.optimize.init is not None else (*dataset_initial_shape(exp, inputs.views), None)


SOURCE = TargetSource("dataset", lambda optimize: bool(optimize.target_dataset), read_dataset, initial=dataset_initial)
