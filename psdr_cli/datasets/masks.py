"""What a dataset's masks must look like to carve a visual hull and weigh a loss (checked on the
views a run fits, :mod:`psdr_cli.target_sources.camera_dataset`): refused before they carve
anything, with the view that shows it.

A pixel is on the object when its mask is at least ½. A view whose mask has no such pixel is
refused (the hull would be carved to nothing or to a fragment); so is a view whose mask covers the
whole image while the masks of other views do not (a mask of every pixel says nothing of the
object; when every view's mask is opaque the dataset is read as having no masks, and a run that
hides the background refuses that on its own). Masks that look inverted are refused: more than
half of the views with a mask of both kinds of pixel are on the object along more than half of
the image border, :data:`BORDER_SHARE`: a photographed object rarely touches most of the frame's
edge, its inverted mask almost always does.
"""
from __future__ import annotations

import numpy as np

from .frames import DatasetError

#: Share of the border pixels on the object above which a view's mask looks inverted.
BORDER_SHARE = 0.5


def border_share(mask: np.ndarray) -> float:
    """Share of the image's outermost pixels (the one-pixel frame) that are on the object."""
    ring = np.concatenate([mask[0], mask[-1], mask[1:-1, 0], mask[1:-1, -1]])
    return float(np.mean(ring >= 0.5))


def check_masks(views: list):
    """Refuses the masks of ``views`` (:class:`~.views.View` records; those without a mask are
    skipped) by the rules of the module docstring."""
    masked = [v for v in views if v.mask is not None]
    for view in masked:
        if not (view.mask >= 0.5).any():
            raise DatasetError(view.source or "dataset", f"frame {view.name} mask",
                               "empty: no pixel on the object (expected white on the object, black around it)")
    opaque = [v for v in masked if v.mask.min() >= 0.999]
    partial = [v for v in masked if v.mask.min() < 0.999]
    if opaque and partial:
        view = opaque[0]
        raise DatasetError(view.source or "dataset", f"frame {view.name} mask",
                           f"covers the whole image, while the masks of {len(partial)} other view(s) do not "
                           f"(expected white on the object, black around it)")
    inverted = [v for v in partial if border_share(v.mask) > BORDER_SHARE]
    if partial and len(inverted) > len(partial) / 2:
        view = inverted[0]
        raise DatasetError(view.source or "dataset", f"frame {view.name} mask",
                           f"looks inverted: in {len(inverted)} of {len(partial)} views the mask is white along "
                           f"most of the image border (expected white on the object, black around it)")
