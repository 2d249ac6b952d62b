"""Decoding photographs and masks into float64 arrays, and resampling them by area.

* 8- and 16-bit PNG and JPEG (and any other format OpenCV decodes to integers) are scaled to
  [0, 1] by 255 or 65535 and, unless ``linear=True``, decoded from sRGB to linear by the exact
  sRGB curve (:func:`srgb_to_linear`). EXR files (and floating-point images) are taken as they
  are: linear.
* Colour is returned *straight* (not premultiplied). PNG stores straight colour; EXR stores
  premultiplied colour (the OpenEXR convention), so an EXR's RGB is divided by its A where
  A > 0.
* The alpha channel (an image's coverage) is returned as an (H, W) array in [0, 1], never
  sRGB-decoded; None when the image has none.
* A separate mask file is grayscale or else its first channel (red), scaled to [0, 1] the same
  way (8-bit by 255, 16-bit by 65535, EXR as is and clipped).
"""
from __future__ import annotations

import os
import struct
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import OpenEXR

from ..support.fileio import image_size, read_exr
from .frames import DatasetError, MissingImage

EXPECTED = "expected a readable PNG, JPEG or EXR image"


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """The exact sRGB decoding curve (IEC 61966-2-1): c / 12.92 for c ≤ 0.04045, else
    ((c + 0.055) / 1.055)^2.4."""
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, np.power((np.maximum(c, 0.04045) + 0.055) / 1.055, 2.4))


def integer_scale(pixels: np.ndarray) -> float:
    """The value of full white of an integer image: 255 for 8 bits, 65535 for 16 bits; 1 for
    floating-point images."""
    if np.issubdtype(pixels.dtype, np.integer):
        return float(np.iinfo(pixels.dtype).max)
    return 1.0


@contextmanager
def held_stderr(held: list):
    """Runs the block with the process's standard error (file descriptor 2, where libpng and
    libjpeg print their complaints about a damaged file) going to a temporary file; its text is
    appended to ``held`` afterwards."""
    sys.stderr.flush()
    try:
        tmp = tempfile.TemporaryFile()
    except OSError:  # nowhere to hold it: the block runs as it is
        yield
        return
    with tmp:
        try:
            saved = os.dup(2)
        except OSError:  # no standard error to hold
            yield
            return
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            held.append(tmp.read().decode("utf-8", "replace"))


def quiet_imdecode(data: np.ndarray, held: list) -> np.ndarray | None:
    """``cv2.imdecode(data, IMREAD_UNCHANGED)`` with OpenCV's warnings and the image libraries'
    own lines about damaged files held back in ``held`` (the caller reports them in one line);
    the log level is restored afterwards."""
    logging = cv2.utils.logging
    level = logging.getLogLevel()
    logging.setLogLevel(min(level, logging.LOG_LEVEL_ERROR))
    try:
        with held_stderr(held):
            return cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    finally:
        logging.setLogLevel(level)


def decode(path: Path, where: str = "") -> np.ndarray:
    """The pixels of a non-EXR image as OpenCV reads them with IMREAD_UNCHANGED (bit depth and
    alpha kept; colour in BGR(A) order), or a :class:`DatasetError` for a missing or corrupt
    file. (Read through numpy so that any path name works.)"""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, where, f"file not found ({EXPECTED})")
    data = np.fromfile(path, dtype=np.uint8)
    held = []
    pixels = quiet_imdecode(data, held) if data.size else None
    if pixels is None or pixels.size == 0:
        said = " ".join(" ".join(held).split())[:160]
        raise DatasetError(path, where, f"cannot be decoded ({f'{said}; ' if said else ''}{EXPECTED})")
    return pixels


def read_exr_image(path: Path, where: str = "") -> tuple[np.ndarray, np.ndarray | None]:
    """(straight linear RGB, alpha or None) of an EXR file with R, G, B (or Y) and optional A
    channels; its premultiplied colour is divided by A where A > 0."""
    try:
        channels = read_exr(path)
    except Exception:  # noqa: BLE001 - OpenEXR raises various types for damaged files
        raise DatasetError(path, where, f"cannot be decoded ({EXPECTED})") from None
    if all(c in channels for c in "RGB"):
        rgb = np.stack([channels[c] for c in "RGB"], axis=-1).astype(np.float64)
    elif "Y" in channels:
        rgb = np.repeat(channels["Y"][..., None].astype(np.float64), 3, axis=-1)
    else:
        names = sorted(k for k in channels if k != "__header__")
        raise DatasetError(path, where, f"has channels {names}, expected R, G, B (or Y) and optionally A")
    alpha = channels["A"].astype(np.float64) if "A" in channels else None
    if alpha is not None:
        rgb = np.where(alpha[..., None] > 0, rgb / np.where(alpha > 0, alpha, 1.0)[..., None], 0.0)
    return rgb, alpha


def read_image(path, *, linear: bool = False, where: str = "") -> tuple[np.ndarray, np.ndarray | None]:
    """(RGB (H, W, 3) float64 linear straight colour, alpha (H, W) in [0, 1] or None) of an
    image file, by the rules of this module's docstring."""
    path = Path(path)
    if path.suffix.lower() == ".exr":
        if not path.is_file():
            raise DatasetError(path, where, f"file not found ({EXPECTED})")
        return read_exr_image(path, where)
    pixels = decode(path, where)
    scale = integer_scale(pixels)
    values = pixels.astype(np.float64) / scale
    if values.ndim == 2:
        values = values[..., None]
    channels = values.shape[2]
    if channels in (1, 2):
        rgb, alpha = np.repeat(values[..., :1], 3, axis=-1), (values[..., 1] if channels == 2 else None)
    else:
        rgb, alpha = values[..., 2::-1], (values[..., 3] if channels >= 4 else None)
    if scale != 1.0 and not linear:
        rgb = srgb_to_linear(rgb)
    return np.ascontiguousarray(rgb), None if alpha is None else np.ascontiguousarray(alpha)


def read_mask(path, *, where: str = "") -> np.ndarray:
    """A separate mask file as (H, W) float64 in [0, 1]: grayscale, or its first channel (red;
    for EXR: Y, else A, else R)."""
    path = Path(path)
    if path.suffix.lower() == ".exr":
        if not path.is_file():
            raise DatasetError(path, where, f"mask file not found ({EXPECTED})")
        try:
            channels = read_exr(path)
        except Exception:  # noqa: BLE001 - OpenEXR raises various types for damaged files
            raise DatasetError(path, where, f"cannot be decoded ({EXPECTED})") from None
        name = next((c for c in ("Y", "A", "R") if c in channels),
                    sorted(k for k in channels if k != "__header__")[0])
        return np.clip(channels[name].astype(np.float64), 0.0, 1.0)
    pixels = decode(path, where)
    first = pixels if pixels.ndim == 2 else pixels[..., 2 if pixels.shape[2] >= 3 else 0]
    return np.clip(first.astype(np.float64) / integer_scale(pixels), 0.0, 1.0)


def image_dimensions(path, file, where: str) -> tuple[int, int]:
    """(width, height) of an image from its header (PNG, JPEG, EXR), else by decoding it; a
    missing or unreadable image is a :class:`DatasetError` naming ``file`` and ``where``."""
    path = Path(path)
    if not path.is_file():
        raise MissingImage(file, where, f"image {path} not found (expected an existing image file)")
    size = image_size(path)
    if size is None:
        try:
            rgb, _ = read_image(path, linear=True)
        except DatasetError as exc:
            raise DatasetError(file, where, f"image {path} {exc.message}") from None
        size = rgb.shape[1], rgb.shape[0]
    return int(size[0]), int(size[1])


def has_alpha(path) -> bool:
    """Whether the image at ``path`` has an alpha channel, from its header where possible: a PNG
    of colour type 4 or 6 (grey or RGB with alpha) or with a tRNS chunk (OpenCV then decodes
    it with alpha); an EXR with an A channel; never a JPEG; any other file by decoding it."""
    path = Path(path)
    if path.suffix.lower() == ".exr":
        with OpenEXR.File(str(path), header_only=True) as f:
            return any(getattr(c, "name", None) == "A" for c in f.header().get("channels", []))
    with open(path, "rb") as f:
        head = f.read(33)
        if head[:2] == b"\xff\xd8":
            return False
        if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
            return head[25] in (4, 6) or png_has_chunk(f, b"tRNS")
    return read_image(path, linear=True)[1] is not None


def png_has_chunk(f, kind: bytes) -> bool:
    """Whether the PNG file ``f``, positioned after its IHDR chunk, has a chunk of ``kind``
    before its image data (chunks skipped by their lengths)."""
    while True:
        header = f.read(8)
        if len(header) < 8 or header[4:] == b"IDAT":
            return False
        if header[4:] == kind:
            return True
        f.seek(struct.unpack(">I", header[:4])[0] + 4, 1)  # data and CRC


def downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """Area averaging by an integer ``factor``: each output pixel is the mean of a
    factor×factor block. An image whose size is not a multiple of ``factor`` is first cropped
    at the right and bottom (at most factor − 1 pixels), which leaves the pixel-corner origin,
    and so cx and cy, unchanged: the caller divides fx, fy, cx, cy by ``factor``. Works on
    (H, W) and (H, W, C) arrays."""
    factor = int(factor)
    if factor == 1:
        return image
    h, w = image.shape[0] // factor, image.shape[1] // factor
    blocks = image[: h * factor, : w * factor].reshape(h, factor, w, factor, *image.shape[2:])
    return blocks.mean(axis=(1, 3))


def resize_area(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """``image`` resampled to width × height by area interpolation (OpenCV INTER_AREA: each
    output pixel averages the input area it covers); (H, W) and (H, W, C) arrays."""
    out = cv2.resize(np.ascontiguousarray(image), (int(width), int(height)), interpolation=cv2.INTER_AREA)
    return out.reshape(int(height), int(width), *image.shape[2:])
