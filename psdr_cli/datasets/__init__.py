"""Camera datasets (photographs and their cameras) read into one common record.

Formats: NeRF-synthetic / Blender (:mod:`.blender`), instant-ngp / nerfstudio
``transforms.json`` (:mod:`.transforms`) and COLMAP sparse models (:mod:`.colmap`), all into
:class:`~.frames.Frame` (OpenCV camera axes, pixel-corner origin); :mod:`.views` decodes them
(:mod:`.images`, :mod:`.undistort`) into :class:`~.views.View` records.
"""
from .frames import DatasetError, Frame
from .views import Splits, View, load_views, read_frames, split_views, view_intrinsics

__all__ = ["DatasetError", "Frame", "Splits", "View", "load_views", "read_frames", "split_views",
           "view_intrinsics"]
