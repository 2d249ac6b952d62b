"""Command-line options checked like the keys they stand for: sample counts, iteration counts,
numbers, views, terms and estimator overrides."""
from __future__ import annotations

from dataclasses import replace

from ..errors import PsdrError
from .experiment_file import Experiment
from .limits import check_paths
from .values import finite32
from .vocabularies import ENGINES, GUIDINGS, SAMPLINGS, TERMS


def option_spp(name: str, spp: int | None, width: int, height: int) -> int | None:
    """A ``--spp``-like command-line value: None, or a positive count within the limits."""
    if spp is None:
        return None
    if spp < 1:
        raise PsdrError(f"{name}: expected a positive number of samples per pixel, got {spp}")
    return check_paths(spp, width, height, lambda m: PsdrError(f"{name}: {m}"))


def option_count(name: str, value: int | None, minimum: int, maximum: int) -> int | None:
    """A count given on the command line (``--iterations``, ``--samples``): None, or an integer
    in [minimum, maximum] (0 is an error, not "the default")."""
    if value is not None and not minimum <= value <= maximum:
        raise PsdrError(f"{name}: expected an integer in [{minimum}, {maximum}], got {value}")
    return value


def option_number(name: str, value: float | None, positive: bool = True) -> float | None:
    """A real-valued command-line option (e.g. ``--fd``): None, or finite in float32 (and > 0)."""
    if value is None:
        return None
    if not finite32(value) or (positive and value <= 0):
        raise PsdrError(f"{name}: expected a finite number{' > 0' if positive else ''}, got {value}")
    return value


def parse_views(views, count: int) -> list[int]:
    """View indices from None (all), a list of ints, or a string like '0,3' or '0-2,5'."""
    if views is None:
        return list(range(count))
    if isinstance(views, str):
        out = []
        for part in filter(None, (p.strip() for p in views.split(","))):
            try:
                if "-" in part:
                    a, b = (int(x) for x in part.split("-", 1))
                    if b < a:
                        raise PsdrError(f"--views: '{part}' is an empty range (expected FIRST-LAST with FIRST <= LAST, "
                                        f"e.g. 0-2)")
                    if not 0 <= a < count or b >= count:   # before the range is built: 0-9999999999
                        raise PsdrError(f"--views: view {a if not 0 <= a < count else b} does not exist "
                                        f"(the experiment has views 0..{count - 1})")
                    out.extend(range(a, b + 1))
                else:
                    out.append(int(part))
            except ValueError:
                raise PsdrError(f"--views: cannot read '{part}' (expected indices like 0,3 or 0-2)") from None
        views = out
    if not views:
        raise PsdrError(f"--views: no view given (expected indices like 0,3 or 0-2; the experiment has views "
                        f"0..{count - 1})")
    bad = [v for v in views if not 0 <= v < count]
    if bad:
        raise PsdrError(f"--views: view {bad[0]} does not exist (the experiment has views 0..{count - 1})")
    return sorted(set(views))


def parse_terms(terms) -> tuple | None:
    """Terms from a comma-separated string or a list, in :data:`TERMS` order (None: None)."""
    if terms is None:
        return None
    names = [t.strip() for t in terms.split(",")] if isinstance(terms, str) else list(terms)
    bad = [t for t in names if t not in TERMS]
    if bad or not names:
        raise PsdrError(f"--terms: unknown term '{bad[0] if bad else ''}' (expected a comma-separated "
                        f"subset of {','.join(TERMS)})")
    return tuple(t for t in TERMS if t in names)


def with_estimator(exp: "Experiment", **overrides) -> "Experiment":
    """The experiment with estimator keys replaced (``None`` values are ignored); values are
    checked like the YAML keys: ``sampling`` in :data:`SAMPLINGS`, ``guiding`` in :data:`GUIDINGS`,
    ``engine`` in :data:`ENGINES`."""
    allowed = {"sampling": SAMPLINGS, "guiding": GUIDINGS, "engine": ENGINES}
    changes = {k: v for k, v in overrides.items() if v is not None}
    for key, value in changes.items():
        if key.endswith("spp"):
            option_spp("--spp", value, exp.scene.width, exp.scene.height)
        if key in allowed and value not in allowed[key]:
            raise PsdrError(f"--{key.replace('_', '-')}: expected one of {', '.join(allowed[key])}, got '{value}'")
    return replace(exp, estimator=replace(exp.estimator, **changes)) if changes else exp
