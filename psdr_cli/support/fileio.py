"""Files psdr reads and writes: EXR images, PNG previews, JSON — always atomically (write, then rename).

A write that fails leaves nothing under the final name and is a :class:`PsdrError` naming the
file: errors of the file system (a full disk, a read-only folder) are reported by Python or, for
EXR and PNG files, by the image libraries, and each image is read back before it is renamed into
place (a library may return as if all went well while the disk filled up under it)."""
from __future__ import annotations

import errno
import json
import os
import stat
import struct
import tempfile
from contextlib import contextmanager
from pathlib import Path

import mitsuba as mi
import numpy as np
import OpenEXR

from ..errors import PsdrError


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

    A reader never sees a half-written file, and an interrupted write leaves the old file intact
    (the file and then its folder are flushed to the disk around the rename: :func:`flush_to_disk`).
    A failure of the file system (the folder is a file or read-only, the disk is full) is raised
    as a :class:`PsdrError` naming ``path``, and so is a ``path`` that is not a regular file
    (:func:`check_output_file`: a folder, a device or a FIFO is never replaced).
    """
    path = Path(path)
    check_output_file(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
        os.close(fd)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file the usual permissions
        yield Path(tmp)
        check_output_file(path)
        flush_to_disk(tmp)
        os.replace(tmp, path)
        flush_to_disk(path.parent)
    except OSError as exc:
        raise PsdrError(f"{path}: cannot write ({describe_os_error(exc)})") from None
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)


def flush_to_disk(path):
    """``fsync`` of a file or folder: a file's bytes are on the disk before it is renamed onto
    its final name, and the rename is, once its folder is flushed (so a power cut leaves the old
    file or the new one, never an empty one)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


#: What a path that is not a regular file is, by the type bits of its mode.
NOT_REGULAR = ((stat.S_ISDIR, "a folder"), (stat.S_ISCHR, "a device"), (stat.S_ISBLK, "a device"),
               (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket"))


def check_output_file(path, option: str = "") -> Path:
    """``path`` if psdr may write a file there: nothing there yet, or a regular file (or a link to
    one), which is replaced whole. A folder, a device (``/dev/null``), a FIFO or a socket, or a
    link to one, is refused with a :class:`PsdrError` naming it (and ``option``, the command-line
    option that gave it): the atomic rename would replace it, not write into it."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):  # nothing there (or no way to tell): the write itself will say
        return path
    kind = next((name for test, name in NOT_REGULAR if test(mode)), None)
    if kind is not None:
        where = f"{path}: {option}: " if option else f"{path}: "
        raise PsdrError(f"{where}not a regular file ({kind}); give the name of a file to write")
    return path


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


#: Errors of the file system that the image libraries report in their messages only.
LIBRARY_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES, errno.EIO)


def library_write(path, tmp, write, read_back):
    """Run an image library's ``write(tmp)``, then check with ``read_back(tmp)`` (True when the
    file holds what was written). OpenEXR and Mitsuba report a failed write as a RuntimeError,
    or not at all (an empty or cut file when the disk fills up as the file is closed); both are
    a :class:`PsdrError` naming ``path`` (:func:`atomic_path` then removes ``tmp``)."""
    try:
        write(str(tmp))
    except RuntimeError as exc:
        text = str(exc)
        reason = next((os.strerror(e) for e in LIBRARY_ERRNOS if os.strerror(e) in text),
                      text.splitlines()[0] if text else type(exc).__name__)
        raise PsdrError(f"{path}: cannot write ({reason})") from None
    try:
        complete = read_back(str(tmp))
    except Exception:  # noqa: BLE001 - a file cut short by the library fails to decode
        complete = False
    if not complete:
        raise PsdrError(f"{path}: cannot write (the file read back is incomplete; is the disk full?)")


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
    def write(tmp):
        with OpenEXR.File(hdr, dict(chans)) as f:  # (OpenEXR turns the dict's arrays into channels)
            f.write(tmp)

    def read_back(tmp):
        written = read_exr(tmp)
        return all(np.array_equal(written.get(name), a) for name, a in chans.items())

    with atomic_path(path) as tmp:
        library_write(path, tmp, write, read_back)


def write_rgb_exr(path, image: np.ndarray, header: dict | None = None):
    """(H, W, 3) image as an RGB EXR."""
    write_exr(path, {c: image[..., i] for i, c in enumerate("RGB")}, header)


def read_exr(path) -> dict:
    """All channels of an EXR file as {name: (H, W) float32}, and the header under '__header__'."""
    with OpenEXR.File(str(path), separate_channels=True) as f:
        out = {name: np.asarray(ch.pixels, np.float32) for name, ch in f.channels().items()}
        out["__header__"] = dict(f.header())
    return out


def image_size(path) -> tuple | None:
    """(width, height) of an image, read from its header alone (no pixel is decoded, so a huge
    image can be refused before it fills the memory): EXR by OpenEXR, PNG and JPEG by their first
    chunk, Radiance HDR by its resolution line, PFM and PPM by their first words, BMP and TGA by
    their fixed headers; None when the header is not recognised (the decoder then says what is
    wrong)."""
    path = Path(path)
    try:
        if path.suffix.lower() == ".exr":
            with OpenEXR.File(str(path), header_only=True) as f:
                lo, hi = f.header()["dataWindow"]
            return int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)
        with open(path, "rb") as f:
            head = f.read(26)
            if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
                return struct.unpack(">II", head[16:24])
            if head[:2] == b"\xff\xd8":
                return _jpeg_size(f)
            if head[:2] == b"#?":
                f.seek(0)
                return _radiance_size(f)
            if head[:2] in (b"PF", b"Pf", b"P2", b"P3", b"P5", b"P6"):
                f.seek(0)
                return _netpbm_size(f.read(4096))
            if head[:2] == b"BM":
                width, height = struct.unpack("<ii", head[18:26])
                return width, abs(height)
        if path.suffix.lower() == ".tga":
            return struct.unpack("<HH", head[12:16])
    except Exception:  # noqa: BLE001 - unreadable or damaged: the decoder reports it
        return None
    return None


def _netpbm_size(head: bytes) -> tuple:
    """(width, height) of a PFM or PPM/PGM file: the magic, then width and height as the next
    two words (``#`` comments skipped); a damaged header raises (:func:`image_size` says None)."""
    words = [w for line in head.split(b"\n") for w in line.split(b"#")[0].split()]
    return int(words[1]), int(words[2])


def _radiance_size(f) -> tuple | None:
    """(width, height) of a Radiance HDR file: header lines up to an empty one, then the
    resolution line, e.g. ``-Y 512 +X 1024`` (height first for the usual orientation)."""
    for _ in range(256):
        line = f.readline(4096).strip()
        if not line:
            break
    words = f.readline(256).split()
    if len(words) != 4:
        return None
    sizes = {words[0][1:]: int(words[1]), words[2][1:]: int(words[3])}
    return sizes[b"X"], sizes[b"Y"]


def image_too_large(path, limit: int) -> str | None:
    """'huge.png is 20000×20000 pixels, more than ...' when the image at ``path`` has more than
    ``limit`` texels by its header (:func:`image_size`), else None."""
    size = image_size(path)
    if size is None or size[0] * size[1] <= limit:
        return None
    return f"{Path(path).name} is {size[0]}×{size[1]} pixels, more than the limit of {limit:,} texels (a resource limit)"


def _jpeg_size(f) -> tuple | None:
    """(width, height) from the first start-of-frame marker of a JPEG file (segments skipped by
    their lengths)."""
    f.seek(2)
    while True:
        marker = f.read(4)
        if len(marker) < 4 or marker[0] != 0xFF:
            return None
        kind, length = marker[1], struct.unpack(">H", marker[2:])[0]
        if 0xC0 <= kind <= 0xCF and kind not in (0xC4, 0xC8, 0xCC):  # SOF0..SOF15 (not DHT, JPG, DAC)
            height, width = struct.unpack(">xHH", f.read(5))
            return width, height
        f.seek(length - 2, os.SEEK_CUR)


def read_rgb_exr(path) -> np.ndarray:
    ch = read_exr(path)
    return np.stack([ch["R"], ch["G"], ch["B"]], axis=-1)


def srgb(linear: np.ndarray) -> np.ndarray:
    """sRGB transfer curve of linear values clipped to [0, 1]."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def write_png(path, rgb8: np.ndarray):
    """(H, W, 3) uint8 image as PNG."""
    rgb8 = np.ascontiguousarray(rgb8, np.uint8)
    with atomic_path(path) as tmp:
        library_write(path, tmp, mi.Bitmap(rgb8, pixel_format=mi.Bitmap.PixelFormat.RGB).write,
                      lambda t: np.array_equal(np.array(mi.Bitmap(t)), rgb8))


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
