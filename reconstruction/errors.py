"""Errors raised by the reconstruction stage.

Every message says what was expected, what was received and what to do, so the CLI can print it as one line.
"""


class ReconstructionError(Exception):
    """Base class for everything the reconstruction stage rejects or cannot do."""


class InputError(ReconstructionError):
    """The source (video or image folder) is missing, unreadable or unusable."""


class RegistrationError(ReconstructionError):
    """Structure from motion did not register enough frames."""


class WorldFrameError(ReconstructionError):
    """The metric, gravity-aligned world frame could not be established (marker, plane, scale)."""


class DenseError(ReconstructionError):
    """Dense stereo measured no depth where the objects stand."""
