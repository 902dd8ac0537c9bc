"""The user-facing pipeline of image2sim: trajectories, physical properties, calibration, diagnosis, CLI.

Public API::

    from grounder import load_trajectories, save_trajectories, Trajectory, TrajectoryError
"""

from grounder._trajectory import (
    Trajectory,
    load_trajectories,
    load_trajectory,
    save_trajectories,
    save_trajectory,
    validate_against_model,
)
from grounder.errors import GrounderError, TrajectoryError

__all__ = [
    "GrounderError",
    "Trajectory",
    "TrajectoryError",
    "load_trajectories",
    "load_trajectory",
    "save_trajectories",
    "save_trajectory",
    "validate_against_model",
]
