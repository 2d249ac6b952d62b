"""The target source ``images`` (``optimize.target.images``): EXR files written by ``psdr render``,
each with the camera it was rendered from in its ``psdr.camera`` header."""
from __future__ import annotations

import glob
import json

import numpy as np

from ..errors import PsdrError
from ..rendering.render import header_camera
from ..support import fileio
from .source import TargetInputs, TargetSource


def image_targets(exp):
    """(images, cameras) from ``target.images`` (EXR files written by ``psdr render``)."""
    pattern = exp.optimize.target_images
    paths = sorted(glob.glob(pattern))
    if not paths:
        raise PsdrError(f"{exp.file}: optimize.target.images: no file matches '{pattern}'")
    images, cameras = [], []
    for p in paths:
        try:
            exr = fileio.read_exr(p)
            cam = json.loads(exr["__header__"]["psdr.camera"])
        except KeyError:
            raise PsdrError(f"{p}: no 'psdr.camera' header (target images must come from `psdr render`)") from None
        except Exception as exc:  # noqa: BLE001 - unreadable EXR
            raise PsdrError(f"{p}: cannot read the EXR target ({str(exc).splitlines()[0] if str(exc) else exc})") from None
        image = np.stack([exr["R"], exr["G"], exr["B"]], -1).astype(np.float64)
        if image.shape[:2] != (exp.scene.height, exp.scene.width):
            raise PsdrError(f"{p}: image is {image.shape[1]}×{image.shape[0]}, but scene.film is "
                            f"{exp.scene.width}×{exp.scene.height}")
        images.append(image)
        try:
            cameras.append(header_camera(cam))
        except (KeyError, TypeError, ValueError):
            raise PsdrError(f"{p}: its 'psdr.camera' header is not a camera written by `psdr render`") from None
    return images, cameras


def read_files(exp) -> TargetInputs:
    """The EXR targets and their cameras (:func:`image_targets`)."""
    images, cameras = image_targets(exp)
    return TargetInputs(images, cameras, None)


SOURCE = TargetSource("images", lambda optimize: bool(optimize.target_images), read_files)
