"""The user-facing pipeline of image2sim: film a scene, calibrate it, learn its residual, diagnose its gap.

Public API: each stage is an options / function / result triple, plus trajectory I/O, `Simulator` and the errors::

    from grounder import GroundOptions, ground, GroundResult                      # grounding/
    from grounder import CalibrateOptions, calibrate, CalibrationResult           # calibration/
    from grounder import DiagnoseOptions, diagnose, Diagnosis                     # diagnosis/
    from grounder import TrackOptions, track, TrackResult                         # tracking/
    from grounder import InteractionOptions, ground_with_interaction, InteractionResult  # interaction/
    from grounder import ResidualOptions, train_residual, ResidualTrainResult, Simulator  # residual/
    from grounder import Trajectory, load_trajectories, save_trajectories, simulate, load_dair_pll_cube  # core/, sim/

The stages are imported on first use (they pull in torch, COLMAP, OpenCV renderers or Ray), so `import grounder`
stays cheap. Where each module lives: docs/layout.md.
"""

from typing import TYPE_CHECKING

from image2sim_common.headless_gl import choose_headless_gl
from image2sim_common.lazy import lazy_attributes
from image2sim_common.outdir import register_record_files

choose_headless_gl()  # before mujoco is imported

import reconstruction  # noqa: E402, F401  (light: its names load on first use; it registers its records)
import scene_export  # noqa: E402, F401  (likewise)
from grounder.core.trajectory import (  # noqa: E402
    Trajectory,
    load_trajectories,
    load_trajectory,
    save_trajectories,
    save_trajectory,
    validate_against_model,
)
from grounder.errors import GrounderError, TrajectoryError  # noqa: E402

# The records grounder's commands write at the top of their output folders (`reconstruction` and `scene_export`
# register theirs when imported, above): a folder holding one is an image2sim output (`image2sim_common.outdir`).
register_record_files(
    "diagnosis.json",
    "calibration.json",
    "residual.json",
    "track.json",
    "variants.json",
    "property_net.json",
    "rollout.json",
)

# name -> module that defines it; resolved on first attribute access (PEP 562). `ground` is among them: it pulls in
# COLMAP, Open3D and trimesh, and the command line starts (`image2sim --help`, a refused option) without them.
_LAZY = {
    "GroundOptions": "grounder.grounding.pipeline",
    "GroundResult": "grounder.grounding.pipeline",
    "ground": "grounder.grounding.pipeline",
    "CalibrateOptions": "grounder.calibration.options",
    "CalibrationResult": "grounder.calibration.result",
    "calibrate": "grounder.calibration.fit",
    "DiagnoseOptions": "grounder.diagnosis.pipeline",
    "Diagnosis": "grounder.diagnosis.result",
    "diagnose": "grounder.diagnosis.pipeline",
    "diagnose_files": "grounder.diagnosis.pipeline",
    "TrackOptions": "grounder.tracking.options",
    "TrackResult": "grounder.tracking.options",
    "track": "grounder.tracking.pipeline",
    "InteractionOptions": "grounder.interaction.options",
    "InteractionResult": "grounder.interaction.options",
    "ground_with_interaction": "grounder.interaction.pipeline",
    "Simulator": "grounder.residual.simulator",
    "has_residual": "grounder.residual.simulator",
    "ResidualOptions": "grounder.residual.options",
    "ResidualTrainResult": "grounder.residual.options",
    "train_residual": "grounder.residual.train",
    "TrackError": "grounder.tracking.options",
    "PropertyModelError": "grounder.properties.model_files",
    "load_dair_pll_cube": "grounder.core.importers",
    "simulate": "grounder.sim.rollout",
}

__getattr__ = lazy_attributes(__name__, _LAZY)


if TYPE_CHECKING:  # what the lazy names are, for type checkers and editors
    from grounder.calibration.fit import calibrate
    from grounder.calibration.options import CalibrateOptions
    from grounder.calibration.result import CalibrationResult
    from grounder.core.importers import load_dair_pll_cube
    from grounder.diagnosis.pipeline import DiagnoseOptions, diagnose, diagnose_files
    from grounder.diagnosis.result import Diagnosis
    from grounder.grounding.pipeline import GroundOptions, GroundResult, ground
    from grounder.interaction.options import InteractionOptions, InteractionResult
    from grounder.interaction.pipeline import ground_with_interaction
    from grounder.properties.model_files import PropertyModelError
    from grounder.residual.options import ResidualOptions, ResidualTrainResult
    from grounder.residual.simulator import Simulator, has_residual
    from grounder.residual.train import train_residual
    from grounder.sim.rollout import simulate
    from grounder.tracking.options import TrackError, TrackOptions, TrackResult
    from grounder.tracking.pipeline import track

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
    "PropertyModelError",
    "ResidualOptions",
    "ResidualTrainResult",
    "Simulator",
    "TrackError",
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
