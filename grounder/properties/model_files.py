"""Where the property model's files live, the error a missing or broken one raises, and the checks their readers
share: the bottom of `grounder.properties`, imported by the prior (`prior`) and the network (`network`) alike."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from grounder.errors import GrounderError, finite_number

# The weights and metadata that ship with the package; `image2sim properties train` regenerates them.
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"


class PropertyModelError(GrounderError):
    """The property model's weights are missing or unreadable, or its input is malformed."""


def finite_numbers(value: Any, length: int) -> bool:
    """A JSON list of `length` numbers, each a `finite_number`."""
    return isinstance(value, list) and len(value) == length and all(finite_number(v) for v in value)
