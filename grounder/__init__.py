"""The user-facing pipeline of image2sim: trajectories, physical properties, calibration, diagnosis, CLI.

Public API::

    from grounder import load_trajectories, save_trajectories, Trajectory, TrajectoryError
"""

import os as _os

# Headless machines have no display for MuJoCo's default GLFW backend: render on the CPU with OSMesa unless the
# user chose a backend (MUJOCO_GL=egl for a GPU). Must happen before mujoco is imported.
if "MUJOCO_GL" not in _os.environ and not _os.environ.get("DISPLAY"):
    _os.environ["MUJOCO_GL"] = "osmesa"
    _os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")


from grounder._ground import GroundOptions, GroundResult, ground
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
    "GroundOptions",
    "GroundResult",
    "GrounderError",
    "Trajectory",
    "TrajectoryError",
    "ground",
    "load_trajectories",
    "load_trajectory",
    "save_trajectories",
    "save_trajectory",
    "validate_against_model",
]
