"""Errors raised by the user-facing pipeline (trajectories, calibration, diagnosis, CLI)."""


class GrounderError(Exception):
    """Base class for everything the grounder rejects; the CLI prints it as one line and exits with code 2."""


class TrajectoryError(GrounderError):
    """A trajectory file or directory does not follow the project's trajectory format."""
