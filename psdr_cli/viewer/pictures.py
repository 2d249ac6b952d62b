"""Images as the viewer sends them: linear HDR arrays tone-mapped to 8-bit sRGB, thumbnails, and
the PNG and EXR files of a run folder read into 8-bit RGB. Reads files; writes nothing."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..support import fileio


def rgb8(linear: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 sRGB of a linear image (clipped to [0, 1]; a grey image is repeated to RGB)."""
    image = np.asarray(linear, np.float64)
    if image.ndim == 2:
        image = image[..., None]
    if image.shape[-1] == 1:
        image = np.repeat(image, 3, axis=-1)
    return np.round(fileio.srgb(image[..., :3]) * 255).astype(np.uint8)


def thumbnail(image: np.ndarray, longest: int = 96) -> np.ndarray:
    """``image`` shrunk (area average) so that its longer side is at most ``longest`` pixels."""
    h, w = image.shape[:2]
    k = max(h, w) / longest
    if k <= 1:
        return image
    return cv2.resize(image, (max(1, round(w / k)), max(1, round(h / k))), interpolation=cv2.INTER_AREA)


def read_png(path: Path) -> np.ndarray | None:
    """(H, W, 3) uint8 RGB of a PNG or JPEG file, None when it cannot be read (absent, being replaced)."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    return None if image is None else cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def read_exr(path: Path) -> np.ndarray | None:
    """8-bit sRGB of a linear RGB EXR file, None when it cannot be read."""
    try:
        return rgb8(fileio.read_rgb_exr(path))
    except Exception:  # noqa: BLE001  (absent, torn or not RGB: the panel stays as it was)
        return None
