"""The target images cached in a run's ``targets/`` folder, trusted only when whole and made
for the run's targets."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..support import fileio


def cached_target(path, key: str, shape: tuple):
    """The cached target image at ``path`` (in ``targets/``) if it can be trusted: it exists,
    reads back whole (not emptied or cut short by a full disk or a copy), was rendered for ``key``
    (:func:`psdr_cli.target_sources.rendered_mesh.target_key`), has the film's (height, width) and finite values; else
    None (the targets are rendered again). A missing file is not read (the EXR library would print
    its own error)."""
    if not Path(path).is_file():
        return None
    try:
        exr = fileio.read_exr(path)
        image = np.stack([exr[c] for c in "RGB"], -1).astype(np.float64)
    except Exception:  # noqa: BLE001 - missing, empty, truncated or not an EXR at all
        return None
    if exr["__header__"].get("psdr.target_key") != key or image.shape[:2] != shape or not np.isfinite(image).all():
        return None
    return image
