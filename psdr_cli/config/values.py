"""Reading an experiment file: a :class:`Section` is one YAML mapping with its key path
(:class:`Where`); each parser checks one value and names the key in its error."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from ..errors import ConfigError
from .limits import FLOAT32_MAX, MAX_COORD, MAX_RADIANCE

#: The default of :meth:`Section.get` for a key that must be given.
REQUIRED = object()


@dataclass
class Where:
    """Location of a value: the experiment file and the dotted key path inside it."""
    file: str
    path: str

    def fail(self, message: str) -> ConfigError:
        return ConfigError(self.file, self.path, message)

    def child(self, key) -> "Where":
        if isinstance(key, int):
            return Where(self.file, f"{self.path}[{key}]")
        return Where(self.file, f"{self.path}.{key}" if self.path else str(key))


Parser = Callable[[Any, Where], Any]


def describe(value) -> str:
    """How ``value`` reads in an error message (``string 'x'``, ``number 3``, a 400-digit integer
    by its length)."""
    if value is None:
        return "nothing"
    if isinstance(value, bool):
        return f"boolean {str(value).lower()}"
    if isinstance(value, int) and abs(value) > FLOAT32_MAX:
        return f"a {len(str(abs(value)))}-digit integer"
    if isinstance(value, (int, float)):
        return f"number {value}"
    if isinstance(value, str):
        return f"string '{value}'"
    if isinstance(value, list):
        if len(value) <= 8 and all(isinstance(v, (int, float, str, bool)) or v is None for v in value):
            return "[" + ", ".join(describe(v) if isinstance(v, int) and abs(v) > FLOAT32_MAX else str(v)
                                   for v in value) + "]"
        return f"a list of {len(value)}"
    if isinstance(value, dict):
        return "a mapping"
    return type(value).__name__


class Section:
    """A YAML mapping being read; :meth:`done` rejects every key that was not read."""

    def __init__(self, data, where: Where):
        if not isinstance(data, dict):
            raise where.fail(f"expected a mapping of keys, got {describe(data)}")
        self.data, self.where, self.used = data, where, set()

    def has(self, key: str) -> bool:
        return self.data.get(key) is not None

    def get(self, key: str, parse: Parser, default=REQUIRED):
        self.used.add(key)
        value = self.data.get(key)
        if value is None:
            if default is REQUIRED:
                raise self.where.child(key).fail("missing (required)")
            return default
        return parse(value, self.where.child(key))

    def done(self):
        unknown = [k for k in self.data if k not in self.used]
        if unknown:
            allowed = ", ".join(sorted(str(k) for k in self.used))
            raise self.where.child(unknown[0]).fail(f"unknown key (expected one of: {allowed})")


def integer(minimum: int | None = None, maximum: int | None = None) -> Parser:
    """An integer in [minimum, maximum]; a bound that is exceeded is named in the message."""
    def parse(value, where):
        if isinstance(value, float) and value.is_integer() and abs(value) < 2 ** 63:
            value = int(value)  # YAML reads 1e12 as a float
        if isinstance(value, bool) or not isinstance(value, int):
            raise where.fail(f"expected an integer, got {describe(value)}")
        got = describe(value) if abs(value) > FLOAT32_MAX else value  # not 400 digits
        if minimum is not None and value < minimum:
            raise where.fail(f"expected an integer >= {minimum}, got {got}")
        if maximum is not None and value > maximum:
            raise where.fail(f"expected an integer <= {maximum} (a resource limit), got {got}")
        return value
    return parse


def finite(value) -> bool:
    """``math.isfinite`` for YAML numbers: an integer too large for a float (400 digits) is not
    finite either (instead of an OverflowError)."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def finite32(value) -> bool:
    """Whether ``value`` is a number that is finite in float32 (the precision it is used in)."""
    return (isinstance(value, (int, float)) and not isinstance(value, bool) and finite(value)
            and abs(value) <= FLOAT32_MAX)


def number(minimum: float | None = None, positive: bool = False, maximum: float | None = None) -> Parser:
    def parse(value, where):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (
                isinstance(value, float) and not math.isfinite(value)):  # (a 400-digit integer: below)
            raise where.fail(f"expected a number, got {describe(value)}")
        if not finite32(value):
            got = describe(value) if isinstance(value, int) else value
            raise where.fail(f"expected a number representable in float32 (|x| <= 3.4e38), got {got}")
        if positive and value <= 0:
            raise where.fail(f"expected a number > 0, got {value}")
        if minimum is not None and value < minimum:
            raise where.fail(f"expected a number >= {minimum}, got {value}")
        if maximum is not None and value > maximum:
            raise where.fail(f"expected a number <= {maximum}, got {value}")
        return float(value)
    return parse


def boolean(value, where):
    if not isinstance(value, bool):
        raise where.fail(f"expected true or false, got {describe(value)}")
    return value


def string(value, where):
    if not isinstance(value, str) or not value.strip():
        raise where.fail(f"expected a non-empty string, got {describe(value)}")
    if "\0" in value:  # no file name (and no folder psdr names after it) can hold one
        raise where.fail("expected a string without NUL characters")
    return value


def choice(*options: str) -> Parser:
    def parse(value, where):
        if not isinstance(value, str):
            raise where.fail(f"expected one of {', '.join(options)}, got {describe(value)}")
        if value not in options:
            raise where.fail(f"unknown '{value}' (expected {', '.join(options)})")
        return value
    return parse


def vector(n: int = 3, nonzero: bool = False, positive: bool = False, bound: float = MAX_COORD) -> Parser:
    """A list of ``n`` finite numbers with |x| ≤ ``bound``."""
    def parse(value, where):
        ok = isinstance(value, (list, tuple)) and len(value) == n and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
        if not ok:
            raise where.fail(f"expected a list of {n} numbers, got {describe(value)}")
        if not all(finite(v) for v in value):
            raise where.fail(f"expected {n} finite numbers, got {describe(list(value))}")
        if max(abs(v) for v in value) > bound:
            raise where.fail(f"expected {n} numbers within ±{bound:g}, got {describe(list(value))}")
        out = tuple(float(v) for v in value)
        if nonzero and not any(out):
            raise where.fail("expected a non-zero vector")
        if positive and min(out) <= 0:
            raise where.fail(f"expected {n} numbers > 0, got {list(value)}")
        return out
    return parse


def color(value, where, maximum: float = MAX_RADIANCE):
    """A non-negative RGB value in [0, ``maximum``]: one number (grey) or [r, g, b]."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value] * 3
    rgb = vector(3, bound=FLOAT32_MAX)(value, where) if isinstance(value, (list, tuple)) else None
    if rgb is None:
        raise where.fail(f"expected a number or a list of 3 numbers, got {describe(value)}")
    if min(rgb) < 0 or max(rgb) > maximum:
        raise where.fail(f"expected non-negative values <= {maximum:g}, got {describe(list(value))}")
    return rgb


def reflectance(value, where):
    """An albedo: one number or [r, g, b] in [0, 1] (energy conservation)."""
    return color(value, where, maximum=1.0)


def scale3(value, where):
    """A positive scale: one number (uniform) or [sx, sy, sz]."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value] * 3
    return vector(3, positive=True)(value, where)


def list_of(parse_item: Parser, min_len: int = 0) -> Parser:
    def parse(value, where):
        if not isinstance(value, list):
            raise where.fail(f"expected a list, got {describe(value)}")
        if len(value) < min_len:
            raise where.fail(f"expected at least {min_len} entr{'y' if min_len == 1 else 'ies'}")
        return [parse_item(v, where.child(i)) for i, v in enumerate(value)]
    return parse


def path_relative_to(base: Path) -> Parser:
    def parse(value, where):
        return (base / string(value, where)).resolve()
    return parse


def unit(v):
    n = math.sqrt(sum(c * c for c in v))
    return tuple(c / n for c in v)


def stage_count_error(where: Where, stages: int, got: int) -> ConfigError:
    return where.fail(f"expected one value, or a list of {stages} (one per remesh stage: the initial shape and "
                      f"each entry of remesh.at), got a list of {got}")


def per_stage(parse_item: Parser, stages: int) -> Parser:
    """One value for the whole run, or a list of one value per remesh stage (the initial shape,
    then each entry of ``remesh.at``), as a tuple."""
    def parse(value, where):
        if not isinstance(value, list):
            return (parse_item(value, where),)
        if len(value) != stages:
            raise stage_count_error(where, stages, len(value))
        return tuple(parse_item(v, where.child(i)) for i, v in enumerate(value))
    return parse
