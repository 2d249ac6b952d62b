"""What psdr asks of a scene's Mitsuba sensors beyond their parameters: whether one is a
perspective camera, and the focal factor σ one carries while a focal length is differentiated.

A focal scale s (f' = s·f, principal point kept) gives the horizontal field of view
2 atan(tan(φ/2) / s) (:func:`scaled_fov`). Its value is written into the sensor's ``x_fov``; its
derivative rides in σ = s / detach(s) (value 1), which a sensor cannot hold as an attribute, so
it is kept here by sensor (:func:`attach`, :func:`factor`) and applied by the camera paths of
:mod:`psdr_cli.estimators.focal`. Writes nothing of the scene.
"""
from __future__ import annotations

import math

import mitsuba as mi


def is_perspective(sensor: mi.Sensor) -> bool:
    """Whether ``sensor`` is Mitsuba's ``perspective`` camera."""
    return sensor.class_name() == "PerspectiveCamera"


#: id(sensor) -> (the sensor, σ): the sensor is held so that its id is not reused meanwhile
_FACTORS: dict = {}


def attach(sensor, sigma) -> None:
    """Let ``sensor`` carry the focal factor σ (an AD Float of value 1), or none (``sigma`` None)."""
    if sigma is None:
        _FACTORS.pop(id(sensor), None)
    else:
        _FACTORS[id(sensor)] = (sensor, mi.Float(sigma))


def factor(sensor):
    """The focal factor σ that ``sensor`` carries (:func:`attach`), or None."""
    entry = _FACTORS.get(id(sensor))
    return None if entry is None or entry[0] is not sensor else entry[1]


def scaled_fov(fov_deg: float, s: float) -> float:
    """The horizontal field of view (degrees) of focal scale ``s``: 2 atan(tan(φ/2) / s)."""
    return math.degrees(2.0 * math.atan(math.tan(math.radians(fov_deg) / 2.0) / s))
