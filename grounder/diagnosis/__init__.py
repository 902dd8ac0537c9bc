"""Sim-to-real gap diagnosis: where the gap between a model and recordings lies, which effect causes it, how far
it shrinks; and the withheld-effect benchmark that checks the diagnosis.

- `pipeline`: `diagnose` and `diagnose_files` (split, where, which, how far).
- `engine`: the setting (`DiagnoseOptions`), batched evaluation of candidate models, the parameter search, scores.
- `where`: the gap by body, contact pair, coordinate, phase and time; where localised effects are tried.
- `targets`: where an effect acts (all, one body, one contact pair) and the model with per-pair contact parameters.
- `measurement`: recording biases fitted on free flight and rest only.
- `tracked`: what ``track.json`` (from `image2sim track`) tells the diagnosis.
- `result`: what a diagnosis found (`Diagnosis`, one `EffectResult` per effect) and its ``diagnosis.json`` content.
- `phases`: the phase of each recorded sample (free flight, impact, sliding, ...) and the gap per phase.
- `gap`: the gap metric: coordinate groups, short-horizon and open-loop windows, batched prediction, scores.
- `effects`: the library of unmodelled effects and recalibrations, each a few parameters applied to a model.
- `noise`: the recording's noise level, estimated, and added to simulated trajectories (the noise floor).
- `outputs`: ``diagnosis.json``, ``report.html`` and ``diagnosed.xml`` written out.
- `report`: the HTML report of a diagnosis.
- `cases`, `benchmark`: the withheld-effect benchmark (synthetic cases with a hidden effect, scored; single- and
  multi-object).

The names load on first use.
"""

from typing import TYPE_CHECKING

from image2sim_common.lazy import lazy_attributes

_LAZY = {
    "DiagnoseOptions": "grounder.diagnosis.pipeline",
    "check_inputs": "grounder.diagnosis.pipeline",
    "diagnose": "grounder.diagnosis.pipeline",
    "diagnose_files": "grounder.diagnosis.pipeline",
    "Diagnosis": "grounder.diagnosis.result",
    "EffectResult": "grounder.diagnosis.result",
    "PHASES": "grounder.diagnosis.phases",
    "detect_phases": "grounder.diagnosis.phases",
    "write_outputs": "grounder.diagnosis.outputs",
    "LIBRARY": "grounder.diagnosis.effects",
    "AppliedEffect": "grounder.diagnosis.effects",
    "Effect": "grounder.diagnosis.effects",
    "apply_effects": "grounder.diagnosis.effects",
    "resolve_effects": "grounder.diagnosis.effects",
    "BENCHMARK": "grounder.diagnosis.cases",
    "MULTI_BODY": "grounder.diagnosis.cases",
    "Target": "grounder.diagnosis.targets",
    "make_case": "grounder.diagnosis.cases",
    "BenchResult": "grounder.diagnosis.benchmark",
    "run_benchmark": "grounder.diagnosis.benchmark",
    "format_table": "grounder.diagnosis.benchmark",
}
__getattr__ = lazy_attributes(__name__, _LAZY)

if TYPE_CHECKING:
    from grounder.diagnosis.benchmark import BenchResult, format_table, run_benchmark
    from grounder.diagnosis.cases import BENCHMARK, MULTI_BODY, make_case
    from grounder.diagnosis.effects import LIBRARY, AppliedEffect, Effect, apply_effects, resolve_effects
    from grounder.diagnosis.outputs import write_outputs
    from grounder.diagnosis.phases import PHASES, detect_phases
    from grounder.diagnosis.pipeline import DiagnoseOptions, check_inputs, diagnose, diagnose_files
    from grounder.diagnosis.result import Diagnosis, EffectResult
    from grounder.diagnosis.targets import Target

__all__ = [
    "BENCHMARK",
    "LIBRARY",
    "MULTI_BODY",
    "PHASES",
    "AppliedEffect",
    "BenchResult",
    "DiagnoseOptions",
    "Diagnosis",
    "Effect",
    "EffectResult",
    "Target",
    "apply_effects",
    "check_inputs",
    "detect_phases",
    "diagnose",
    "diagnose_files",
    "format_table",
    "make_case",
    "resolve_effects",
    "run_benchmark",
    "write_outputs",
]
