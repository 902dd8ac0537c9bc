"""The user-facing pipeline of image2sim: trajectories, physical properties, calibration, diagnosis, CLI.

Public API::

    from grounder import ground, load_trajectories, save_trajectories, Trajectory, TrajectoryError
    from grounder import calibrate, diagnose, track, ground_with_interaction, Simulator, load_dair_pll_cube

The later stages are imported on first use (they pull in torch, OpenCV renderers or Ray), so `import grounder`
stays cheap.
"""

import os as _os

# Headless machines have no display for MuJoCo's default GLFW backend: render on the CPU with OSMesa unless the
# user chose a backend (MUJOCO_GL=egl for a GPU). Must happen before mujoco is imported.
if "MUJOCO_GL" not in _os.environ and not _os.environ.get("DISPLAY"):
    _os.environ["MUJOCO_GL"] = "osmesa"
    _os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")


from typing import TYPE_CHECKING

from grounder._trajectory import (
    Trajectory,
    load_trajectories,
    load_trajectory,
    save_trajectories,
    save_trajectory,
    validate_against_model,
)
from grounder.errors import GrounderError, TrajectoryError

# name -> module that defines it; resolved on first attribute access (PEP 562). `ground` is among them: it pulls in
# COLMAP, Open3D and trimesh, and the command line starts (`image2sim --help`, a refused option) without them.
_LAZY = {
    "GroundOptions": "grounder._ground",
    "GroundResult": "grounder._ground",
    "ground": "grounder._ground",
    "CalibrateOptions": "grounder._calibrate",
    "CalibrationResult": "grounder._calibrate",
    "calibrate": "grounder._calibrate",
    "DiagnoseOptions": "grounder._diagnose",
    "Diagnosis": "grounder._diagnose",
    "diagnose": "grounder._diagnose",
    "diagnose_files": "grounder._diagnose",
    "TrackOptions": "grounder._track",
    "TrackResult": "grounder._track",
    "track": "grounder._track",
    "InteractionOptions": "grounder._interaction",
    "InteractionResult": "grounder._interaction",
    "ground_with_interaction": "grounder._interaction",
    "Simulator": "grounder._simulator",
    "has_residual": "grounder._simulator",
    "ResidualOptions": "grounder._residual_train",
    "train_residual": "grounder._residual_train",
    "load_dair_pll_cube": "grounder._import",
    "simulate": "grounder._simulate",
}


def __getattr__(name: str) -> object:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'grounder' has no attribute {name!r}")


if TYPE_CHECKING:  # what the lazy names are, for type checkers and editors
    from grounder._calibrate import CalibrateOptions, CalibrationResult, calibrate
    from grounder._diagnose import DiagnoseOptions, Diagnosis, diagnose, diagnose_files
    from grounder._ground import GroundOptions, GroundResult, ground
    from grounder._import import load_dair_pll_cube
    from grounder._interaction import InteractionOptions, InteractionResult, ground_with_interaction
    from grounder._residual_train import ResidualOptions, train_residual
    from grounder._simulate import simulate
    from grounder._simulator import Simulator, has_residual
    from grounder._track import TrackOptions, TrackResult, track

__all__ = [  # spelled out (not built from _LAZY) so that linters and type checkers read it
    "CalibrateOptions",
    "CalibrationResult",
    "DiagnoseOptions",
    "Diagnosis",
    "GroundOptions",
    "GroundResult",
    "GrounderError",
    "InteractionOptions",
    "InteractionResult",
    "ResidualOptions",
    "Simulator",
    "TrackOptions",
    "TrackResult",
    "Trajectory",
    "TrajectoryError",
    "calibrate",
    "diagnose",
    "diagnose_files",
    "ground",
    "ground_with_interaction",
    "has_residual",
    "load_dair_pll_cube",
    "load_trajectories",
    "load_trajectory",
    "save_trajectories",
    "save_trajectory",
    "simulate",
    "track",
    "train_residual",
    "validate_against_model",
]
