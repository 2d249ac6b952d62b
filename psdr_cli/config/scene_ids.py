"""The Mitsuba ids psdr gives its own scene entries (cameras, emitters, the integrator) and the
names a scene object may not have."""
from __future__ import annotations

#: First character of the Mitsuba ids psdr gives its own scene entries (cameras, emitters, the
#: integrator): no object name may start with it, so user names never meet psdr's.
INTERNAL_PREFIX = "@"
INTEGRATOR_ID = INTERNAL_PREFIX + "integrator"


def sensor_id(i: int) -> str:
    """Mitsuba id of camera ``i`` (``@sensor_000``)."""
    return f"{INTERNAL_PREFIX}sensor_{i:03d}"


def emitter_id(i: int) -> str:
    """Mitsuba id of emitter ``i`` (``@emitter_00``)."""
    return f"{INTERNAL_PREFIX}emitter_{i:02d}"


def name_problem(name: str) -> str | None:
    """Why ``name`` cannot name a scene object (a Mitsuba id beside psdr's own), or None."""
    if name.startswith(INTERNAL_PREFIX):
        return (f"'{name}' is reserved (names starting with '{INTERNAL_PREFIX}' are psdr's own ids for cameras, "
                f"emitters and the integrator); choose another name")
    if name == "type":
        return "'type' is reserved (Mitsuba's scene dictionary uses it); choose another name"
    if "." in name:
        return f"'{name}' contains '.', which separates Mitsuba parameter names (use '_')"
    return None
