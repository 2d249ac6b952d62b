"""``optimize.target.dataset``: photographs and their cameras as an optimisation's targets."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .limits import MAX_FILM
from .values import Parser, Section, boolean, choice, integer, number, string, vector
from .vocabularies import BACKGROUNDS, DATASET_FORMATS


@dataclass
class DatasetConfig:
    """``optimize.target.dataset``: photographs and their cameras (:mod:`psdr_cli.datasets`)."""
    path: Path
    key: str                               # "<experiment file>: <key path>", for error messages
    format: str = "auto"                   # auto | blender | transforms | colmap
    images: Path | None = None             # colmap: the image folder (default: <path>/images, <path>/../../images)
    masks: Path | None = None              # colmap: a folder of mask PNGs named after the images
    downsample: int = 1                    # area-average factor applied to every image (and its intrinsics)
    linear: bool = False                   # PNG/JPEG values are linear already (default: sRGB-encoded)
    holdout_every: int | None = None       # None: the dataset's own splits; k: every k-th frame is held out
    background: str = "auto"               # auto (hidden when the views have masks) | hidden | visible
    silhouette: float = 1.0                # weight of the silhouette loss mean|C − M| of masked views (0: off)
    up: tuple | None = None                # the dataset world's up axis (None: found from the cameras)
    frame: tuple | None = None             # not a YAML key: (s, c) of the normalised frame, filled when loaded
    split: str = "train"                   # not a YAML key: the views the scene's cameras are (train | test | all)


def parse_dataset(base: Path) -> Parser:
    """``optimize.target.dataset``: a folder (or a ``transforms*.json`` file, or a COLMAP model
    folder) of photographs with their cameras; paths relative to the experiment file."""
    def folder(value, where):
        path = Path(string(value, where))
        return path if path.is_absolute() else base / path

    def parse(value, where) -> DatasetConfig:
        if isinstance(value, str):
            value = {"path": value}
        sec = Section(value, where)
        d = DatasetConfig(path=sec.get("path", folder), key=f"{where.file}: {where.path}")
        d.format = sec.get("format", choice(*DATASET_FORMATS), d.format)
        d.images = sec.get("images", folder, None)
        d.masks = sec.get("masks", folder, None)
        d.downsample = sec.get("downsample", integer(1, MAX_FILM), d.downsample)
        d.linear = sec.get("linear", boolean, d.linear)
        d.holdout_every = sec.get("holdout_every", integer(2, MAX_FILM), None)
        d.background = sec.get("background", choice(*BACKGROUNDS), d.background)
        d.silhouette = sec.get("silhouette", number(minimum=0), d.silhouette)
        d.up = sec.get("up", vector(3, nonzero=True), None)
        sec.done()
        if not d.path.exists():
            raise where.child("path").fail(f"not found: {d.path}")
        return d
    return parse
