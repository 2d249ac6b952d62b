"""Reading the JSON camera files of the Blender and transforms.json formats: the file, its
numbers, its frame list and its image paths, each failure one :class:`DatasetError` line."""
from __future__ import annotations

import json
import math
from pathlib import Path

from .frames import DatasetError, MissingImage


def read_json(path: Path) -> dict:
    """The JSON object in ``path``; a missing file, invalid JSON (with its line and column) or a
    top level that is not an object is a :class:`DatasetError`."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "", "file not found (expected a JSON camera file)")
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))  # (a byte order mark, as some editors write, is read)
    except json.JSONDecodeError as exc:
        raise DatasetError(path, f"line {exc.lineno} column {exc.colno}",
                           f"not valid JSON ({exc.msg})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(path, "", f"cannot be read as UTF-8 JSON ({exc})") from None
    if not isinstance(data, dict):
        raise DatasetError(path, "", f"expected a JSON object at the top level, got {type(data).__name__}")
    return data


def number(value, file, key: str, *, positive: bool = False) -> float:
    """``value`` as a finite float (> 0 when ``positive``), else a :class:`DatasetError`."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or (positive and value <= 0):
        kind = "a positive number" if positive else "a finite number"
        raise DatasetError(file, key, f"expected {kind}, got {json.dumps(value)}")
    return float(value)


#: The fields of view a camera may have, in radians: more than 1°, less than 170°.
FOV_RANGE = (math.radians(1.0), math.radians(170.0))


def field_of_view(value, file, key: str) -> float:
    """``value`` as a field of view in radians inside :data:`FOV_RANGE`, else a
    :class:`DatasetError` (which calls a value from 3.2 to 180 "degrees, by the look of it")."""
    fov = number(value, file, key, positive=True)
    if FOV_RANGE[0] < fov < FOV_RANGE[1]:
        return fov
    hint = f"; {fov:g} looks like degrees ({math.radians(fov):.4g} rad)" if 3.2 <= fov <= 180.0 else ""
    raise DatasetError(file, key, f"{fov:g}: expected a field of view in radians between 1° and 170° "
                                  f"({FOV_RANGE[0]:.4f} to {FOV_RANGE[1]:.4f}){hint}")


def focal_length(value, file, key: str) -> float:
    """``value`` as a focal length of at least one pixel, else a :class:`DatasetError`."""
    focal = number(value, file, key, positive=True)
    if focal < 1.0:
        raise DatasetError(file, key, f"{focal:g}: expected a focal length of at least 1 px")
    return focal


def frame_list(data: dict, file) -> list:
    """The non-empty list under ``frames``, each entry an object."""
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        got = "nothing" if frames is None else json.dumps(frames)[:40]
        raise DatasetError(file, "frames", f"expected a non-empty list of frames, got {got}")
    for i, entry in enumerate(frames):
        if not isinstance(entry, dict):
            raise DatasetError(file, f"frames[{i}]", "expected an object with file_path and transform_matrix")
    return frames


def relative_path(value, file, key: str) -> str:
    """A relative path string as written (``./`` prefixes removed), else a :class:`DatasetError`."""
    if not isinstance(value, str) or not value.strip():
        raise DatasetError(file, key, f"expected a relative image path, got {json.dumps(value)}")
    text = value.strip().replace("\\", "/")
    while text.startswith("./"):
        text = text[2:]
    return text


def image_path(folder: Path, relative: str, file, key: str, default_suffix: str = ".png") -> Path:
    """The existing file ``folder / relative``; a path without an extension that does not exist
    as written gets ``default_suffix``. A missing file is a :class:`MissingImage`."""
    path = folder / relative
    if path.is_file():
        return path
    if not Path(relative).suffix:
        candidate = path.with_name(path.name + default_suffix)
        if candidate.is_file():
            return candidate
        raise MissingImage(file, key, f"image {path} (or {candidate.name}) not found (expected an existing image file)")
    raise MissingImage(file, key, f"image {path} not found (expected an existing image file)")
