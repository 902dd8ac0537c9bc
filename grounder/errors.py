"""Errors raised by the user-facing pipeline (trajectories, calibration, diagnosis, CLI)."""

import json
import math
import numbers


class GrounderError(Exception):
    """Base class for everything the grounder rejects; the CLI prints it as one line and exits with code 2."""


class TrajectoryError(GrounderError):
    """A trajectory file or directory does not follow the project's trajectory format."""


def shown(value: object, limit: int = 60) -> str:
    """A value read from a user's file (JSON, YAML, metadata) for a one-line error: as JSON writes it (so a file's
    `"4"` shows as `"4"`, its `null` as `null`, a NaN as `NaN`), otherwise as Python does, cut to `limit` characters."""
    try:
        text = json.dumps(value, ensure_ascii=True)
    except (TypeError, ValueError, RecursionError):
        text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def finite_number(value: object) -> bool:
    """A real number from a user's file or call (Python's or NumPy's; not a bool) that is finite as a float (a
    huge integer is not)."""
    if not isinstance(value, numbers.Real) or isinstance(value, bool):  # NumPy's bool_ is not a numbers.Real
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False


def integer_in(value: object, low: int, high: int | None = None) -> bool:
    """An integer from a user's file or call (Python's or NumPy's; not a bool, not a whole float) in [low, high]
    (no upper end when ``high`` is None)."""
    if not isinstance(value, numbers.Integral) or isinstance(value, bool):  # NumPy's bool_ is not Integral
        return False
    return low <= int(value) and (high is None or int(value) <= high)
