"""Calibration: fit a scene's physical parameters (or its objects' property embeddings) to recorded trajectories.

- `fit`: `calibrate`, the entry point (how it fits: its module docstring), and the train/validation split;
- `options`: `CalibrateOptions`, the settings of one calibration;
- `result`: `CalibrationResult`, `ParameterFit`, `ErrorSummary`, what a calibration returns;
- `parameters`: parameter names, bounds and defaults, and applying values to a model or spec;
- `evaluator`: `Evaluator`, the batched losses of candidate parameter vectors;
- `search`: differential evolution, least squares, intervals in the unit box of the parameters;
- `embedding`: embedding mode, the property embedding as the searched quantity;
- `scene_output`: writing the calibrated scene folder;
- `report`: the calibration's ``report.html``;
- `batch`: many calibrations on Ray, resumable; `batch_jobs`: its jobs file; `batch_output`: its output folder;
- `distribution`: ``--distribution``, a fitted distribution over the parameters (``distribution.json``);
- `randomize`: domain-randomisation variants drawn from it (``image2sim randomize``);
- `known_case`: tosses whose friction and damping ratio vary with a known mean and spread (the fit's check).

The names below are loaded on first use (PEP 562), so that importing one module does not import them all.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from image2sim_common.lazy import lazy_attributes

# name -> module that defines it
_LAZY = {
    "calibrate": "grounder.calibration.fit",
    "split_names": "grounder.calibration.fit",
    "CalibrateOptions": "grounder.calibration.options",
    "CalibrationResult": "grounder.calibration.result",
    "ErrorSummary": "grounder.calibration.result",
    "ParameterFit": "grounder.calibration.result",
    "Parameter": "grounder.calibration.parameters",
    "apply_to_model": "grounder.calibration.parameters",
    "apply_to_spec": "grounder.calibration.parameters",
    "resolve_parameters": "grounder.calibration.parameters",
    "Evaluator": "grounder.calibration.evaluator",
    "write_calibrated_scene": "grounder.calibration.scene_output",
    "write_report": "grounder.calibration.report",
    "BatchSummary": "grounder.calibration.batch",
    "run_batch": "grounder.calibration.batch",
    "Job": "grounder.calibration.batch_jobs",
    "load_jobs": "grounder.calibration.batch_jobs",
    "FittedDistribution": "grounder.calibration.distribution",
    "read_distribution": "grounder.calibration.distribution",
    "write_randomized_variants": "grounder.calibration.randomize",
}


__getattr__ = lazy_attributes(__name__, _LAZY)


if TYPE_CHECKING:  # what the lazy names are, for type checkers and editors
    from grounder.calibration.batch import BatchSummary, run_batch
    from grounder.calibration.batch_jobs import Job, load_jobs
    from grounder.calibration.distribution import FittedDistribution, read_distribution
    from grounder.calibration.evaluator import Evaluator
    from grounder.calibration.fit import calibrate, split_names
    from grounder.calibration.options import CalibrateOptions
    from grounder.calibration.parameters import Parameter, apply_to_model, apply_to_spec, resolve_parameters
    from grounder.calibration.randomize import write_randomized_variants
    from grounder.calibration.report import write_report
    from grounder.calibration.result import CalibrationResult, ErrorSummary, ParameterFit
    from grounder.calibration.scene_output import write_calibrated_scene

__all__ = [  # spelled out (not built from _LAZY) so that linters and type checkers read it
    "BatchSummary",
    "CalibrateOptions",
    "CalibrationResult",
    "ErrorSummary",
    "Evaluator",
    "FittedDistribution",
    "Job",
    "Parameter",
    "ParameterFit",
    "apply_to_model",
    "apply_to_spec",
    "calibrate",
    "load_jobs",
    "read_distribution",
    "resolve_parameters",
    "run_batch",
    "split_names",
    "write_calibrated_scene",
    "write_randomized_variants",
    "write_report",
]
