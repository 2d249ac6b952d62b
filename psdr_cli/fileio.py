"""Files psdr reads and writes: EXR images, PNG previews, JSON — always atomically (write, then rename)."""
from __future__ import annotations

import json
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

import mitsuba as mi
import numpy as np
import OpenEXR

from .errors import PsdrError


def temporaries(folder) -> list:
    """Temporary files of :func:`atomic_path` under ``folder`` (``.<stem>.<random>.tmp<suffix>``):
    left behind only by a process killed in the middle of a write."""
    folder = Path(folder)
    return sorted(p for p in folder.rglob(".*.tmp*") if p.is_file()) if folder.is_dir() else []


def remove_temporaries(folder) -> int:
    """Delete the leftover temporaries under ``folder`` (call only while no process writes
    there, e.g. holding the run's lock); returns how many were removed."""
    found = temporaries(folder)
    for path in found:
        path.unlink(missing_ok=True)
    return len(found)


@contextmanager
def atomic_path(path):
    """Yield a temporary path next to ``path``; rename it onto ``path`` only if the block succeeds.

    A reader never sees a half-written file, and an interrupted write leaves the old file intact.
    A failure of the file system (the folder is a file or read-only, the disk is full) is raised
    as a :class:`PsdrError` naming ``path``.
    """
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
        os.close(fd)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file the usual permissions
        yield Path(tmp)
        if path.is_dir():
            raise IsADirectoryError(21, "Is a directory")
        os.replace(tmp, path)
    except OSError as exc:
        raise PsdrError(f"{path}: cannot write ({describe_os_error(exc)})") from None
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)


def writable_folder(folder) -> Path:
    """``folder``, created if missing, once a file could be created in it; else a
    :class:`PsdrError` naming it (checked before long work, so that it fails at once)."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".psdr-write-test.", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise PsdrError(f"{folder}: cannot write the output folder ({describe_os_error(exc)})") from None
    return folder


def describe_os_error(exc: OSError) -> str:
    """'No space left on device', 'Permission denied', ... naming the file when it is another one."""
    text = exc.strerror or type(exc).__name__
    return f"{text}: {exc.filename}" if exc.filename else text


def check_finite(path, array, what: str):
    """Raise a :class:`PsdrError` naming ``path`` when ``array`` holds NaN or infinite values
    (psdr never writes such a file)."""
    bad = int(np.size(array) - np.count_nonzero(np.isfinite(array)))
    if bad:
        raise PsdrError(f"{path}: not written: the {what} has {bad} NaN or infinite values "
                        f"(check radiances, scales, coordinates and sample counts)")


def write_exr(path, channels: dict, header: dict | None = None):
    """Multi-channel float32 EXR. ``channels`` maps names ('R', 'direct.G', ...) to (H, W) arrays;
    ``header`` entries are stored as string attributes (tev and OpenEXR tools show them)."""
    chans = {name: np.ascontiguousarray(a, np.float32) for name, a in channels.items()}
    for name, a in chans.items():
        check_finite(path, a, f"image channel {name}")
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for key, value in (header or {}).items():
        hdr[key] = value if isinstance(value, str) else json.dumps(value)
    with atomic_path(path) as tmp:
        with OpenEXR.File(hdr, chans) as f:
            f.write(str(tmp))


def write_rgb_exr(path, image: np.ndarray, header: dict | None = None):
    """(H, W, 3) image as an RGB EXR."""
    write_exr(path, {c: image[..., i] for i, c in enumerate("RGB")}, header)


def read_exr(path) -> dict:
    """All channels of an EXR file as {name: (H, W) float32}, and the header under '__header__'."""
    with OpenEXR.File(str(path), separate_channels=True) as f:
        out = {name: np.asarray(ch.pixels, np.float32) for name, ch in f.channels().items()}
        out["__header__"] = dict(f.header())
    return out


def read_rgb_exr(path) -> np.ndarray:
    ch = read_exr(path)
    return np.stack([ch["R"], ch["G"], ch["B"]], axis=-1)


def srgb(linear: np.ndarray) -> np.ndarray:
    """sRGB transfer curve of linear values clipped to [0, 1]."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def write_png(path, rgb8: np.ndarray):
    """(H, W, 3) uint8 image as PNG."""
    with atomic_path(path) as tmp:
        mi.Bitmap(np.ascontiguousarray(rgb8, np.uint8), pixel_format=mi.Bitmap.PixelFormat.RGB).write(str(tmp))


def write_preview(path, image: np.ndarray, exposure: float = 0.0):
    """Tone-mapped PNG of a linear HDR image: scale by 2^exposure, clip, sRGB."""
    write_png(path, np.round(srgb(image * 2.0 ** exposure) * 255).astype(np.uint8))


def write_json(path, data):
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, default=str) + "\n")


def diverging(values: np.ndarray, scale: float) -> np.ndarray:
    """(H, W) signed values → (H, W, 3) uint8: blue (−scale) · white (0) · red (+scale)."""
    t = np.clip(values / scale, -1.0, 1.0) if scale > 0 else np.zeros_like(values)
    pos, neg = np.clip(t, 0, 1), np.clip(-t, 0, 1)
    rgb = np.stack([1 - neg, 1 - pos - neg, 1 - pos], axis=-1)
    return np.round(srgb(np.clip(rgb, 0, 1)) * 255).astype(np.uint8)


def write_gradient_preview(path, gradient: np.ndarray, scale: float):
    """PNG of a gradient image (channel mean) with a symmetric diverging colour map at ±``scale``."""
    write_png(path, diverging(gradient.mean(axis=-1), scale))
